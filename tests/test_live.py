"""The live service over loopback: replay -> live -> a viewer that receives the volume, which equals
``usdeform correct --volume`` of the recording the service wrote; faults (a malformed message, a
frame without a pose, a dropped connection, a viewer that goes away) are logged and the service goes on."""

from __future__ import annotations

import dataclasses
import json
import logging
import socket
import struct
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from live_helpers import N_FRAMES, free_port, scan_fixture, serve  # noqa: E402
from usdeform.cli import main  # noqa: E402
from usdeform.correction import correct_recording  # noqa: E402
from usdeform.errors import FileFormatError, InputError  # noqa: E402
from usdeform.io import read_sequence, read_volume, save_model  # noqa: E402
from usdeform.live import LiveClient, LiveServer, OutputSettings, ScalarSource, StreamSettings, replay  # noqa: E402
from usdeform.live.engine import FrameStore, LiveVolume  # noqa: E402
from usdeform.live.pairing import PairedFrame, Pairer, image_delay_from_diagnosis  # noqa: E402
from usdeform.regression import VesselAnchor, VesselAnchoredModel  # noqa: E402
from usdeform.volume import Compounder, Volume  # noqa: E402

scan = scan_fixture("live")


def _offline_volume(recording: Path, model: Path) -> Volume:
    """``usdeform correct --volume`` of ``recording``."""
    out = recording.with_name("offline.nrrd")
    args = ["correct", str(recording), "--model", str(model), "--output", str(recording.with_name("c.seq.nrrd"))]
    assert main([*args, "--volume", str(out)]) == 0
    return read_volume(out)


@pytest.fixture(scope="module")
def anchored_scan(scan, tmp_path_factory) -> dict[str, Any]:
    """The synthetic sweep with a vessel-anchored model (``usdeform fit``'s default kind): the scan's model as
    its image part and a vessel part on the sweep's dark lumen."""
    folder = tmp_path_factory.mktemp("live-anchored")
    rows, cols = scan["model"].frame_shape
    coefficients = np.random.default_rng(5).normal(0.0, 0.3, (2, 3, 3, 3))
    reference = VesselAnchor((cols / 2, rows * 0.55), float(np.sqrt(cols / 6 * rows / 8)))
    model = VesselAnchoredModel(scan["model"], coefficients, reference)
    save_model(folder / "model.json", model, scan["sampled"])
    return {**scan, "folder": folder, "model": model}


def test_replay_live_viewer_volume_equals_offline_correct(scan, tmp_path: Path) -> None:
    _check_live_volume_equals_offline_correct(scan, tmp_path)


def test_a_vessel_anchored_model_follows_the_lumen_across_batches_as_offline(anchored_scan, tmp_path: Path) -> None:
    """The default model kind: the lumen searched batch after batch from where the last batch left it, so the
    volume is ``usdeform correct --volume``'s of the recording, in which the lumen is searched in one pass."""
    _check_live_volume_equals_offline_correct(anchored_scan, tmp_path)


def _check_live_volume_equals_offline_correct(scan: dict[str, Any], tmp_path: Path) -> Any:
    record = tmp_path / "live.seq.nrrd"
    server, thread, out = serve(scan, record=record, outputs=OutputSettings(volume_rate_hz=10.0))
    viewer = LiveClient(("127.0.0.1", server.port))
    sent = replay(scan["sweep"], ("127.0.0.1", server.port), rate_hz=60.0)
    thread.join(timeout=60.0)
    time.sleep(0.2)
    viewer.close()
    result = out["result"]
    assert sent.frames_sent == N_FRAMES
    assert (result.images_read, result.frames_corrected, result.malformed) == (N_FRAMES, N_FRAMES, 0)
    assert result.skipped == {}
    volumes = viewer.named("CorrectedVolume")
    assert volumes and volumes[-1].metadata["FramesInserted"] == str(N_FRAMES)
    assert viewer.named("CorrectedImage") and viewer.named("usdeformStatus")
    # The last volume sent is usdeform correct --volume of the recording, voxel for voxel.
    offline = _offline_volume(record, scan["folder"] / "model.json")
    assert np.array_equal(volumes[-1].image, offline.image)
    assert np.allclose(volumes[-1].ijk_to_world_matrix, offline.index_to_world, atol=1e-4)
    # The volumes streamed during the scan (on a grid with room to grow) hold the same corrected frames.
    live_grid = server._volume.compounder.grid  # type: ignore[union-attr]
    streamed = [m for m in volumes[:-1] if m.metadata["FramesInserted"] == str(N_FRAMES)]
    corrected = correct_recording(read_sequence(record), scan["model"], scan["sampled"])
    compounder = Compounder(live_grid)
    compounder.add_frames(corrected.frames, corrected.image_to_base, valid=corrected.pixel_valid)
    # The volume sent is the part of the grid the frames reach: its origin is a voxel of the grid.
    x, y, z = np.round((streamed[-1].ijk_to_world_matrix[:3, 3] - live_grid.origin) / live_grid.spacing).astype(int)
    depth, rows, cols = streamed[-1].image.shape
    assert np.array_equal(streamed[-1].image, compounder.volume().image[z : z + depth, y : y + rows, x : x + cols])
    # The recording holds what was received: the frames bit for bit.
    assert np.array_equal(read_sequence(record).frames, scan["sweep"].frames)
    return result


@pytest.mark.parametrize("kind", ["scan", "anchored_scan"])
def test_a_growing_grid_and_the_final_volume_use_the_frames_corrected_once(
    kind, request, tmp_path, monkeypatch
) -> None:
    """Each batch is corrected once, when it is added: a grid that grows several times and the final volume
    are compounded from the corrected frames the store keeps (no correction again), and are still the
    correction of the recording in one pass (``usdeform correct --volume``), voxel for voxel."""
    scan = request.getfixturevalue(kind)
    corrected_sizes: list[int] = []

    def counted(recording: Any, *args: Any, **kwargs: Any) -> Any:
        corrected_sizes.append(len(recording))
        return correct_recording(recording, *args, **kwargs)

    monkeypatch.setattr("usdeform.live.engine.correct_recording", counted)
    sweep = scan["sweep"]
    store = FrameStore(sweep.shape, sweep.image_to_probe, with_displacement=True, directory=tmp_path)
    live = LiveVolume(store, scan["model"], scan["sampled"], stiffness_source="sweep", margin_mm=0.5)
    assert sweep.force is not None and sweep.probe_displacement is not None
    batches = [range(start, min(start + 3, N_FRAMES)) for start in range(0, N_FRAMES, 3)]
    try:
        for number, batch in enumerate(batches):
            frames = [
                PairedFrame(
                    i,
                    float(sweep.timestamps[i]),
                    sweep.frames[i],
                    sweep.probe_to_base[i],
                    float(sweep.force[i]),
                    float(sweep.probe_displacement[i]),
                    0.0,
                )
                for i in batch
            ]
            live.add(store.append(frames))
            live.poll(wait=number % 2 == 1)  # a grown grid taken as soon as it is ready, or waited for
        final = live.final_volume()
        store.write(tmp_path / "live.seq.nrrd", {})
        live_grid = live.compounder.grid  # type: ignore[union-attr]
        live_image = live.compounder.volume().image  # type: ignore[union-attr]
    finally:
        store.close()
    assert live.regrown >= 3
    assert corrected_sizes == [len(batch) for batch in batches]  # the correction of each batch, in add only
    assert final is not None and live.frames_inserted == N_FRAMES
    offline = _offline_volume(tmp_path / "live.seq.nrrd", scan["folder"] / "model.json")
    assert np.array_equal(final.image, offline.image)
    assert np.allclose(final.index_to_world, offline.index_to_world, atol=1e-4)
    # The grown grid holds every frame corrected as in one pass over the recording.
    corrected = correct_recording(read_sequence(tmp_path / "live.seq.nrrd"), scan["model"], scan["sampled"])
    compounder = Compounder(live_grid)
    compounder.add_frames(corrected.frames, corrected.image_to_base, valid=corrected.pixel_valid)
    assert np.array_equal(live_image, compounder.volume().image)


def test_usdeform_replay_and_usdeform_live_end_to_end(scan, tmp_path: Path, capsys) -> None:
    folder, port = scan["folder"], free_port()
    record, volume = tmp_path / "scan.seq.nrrd", tmp_path / "live.nrrd"
    args = ["live", "--model", str(folder / "model.json"), "--listen", f"127.0.0.1:{port}", "--record", str(record)]
    args += ["--volume", str(volume), "--idle-stop", "1", "--max-seconds", "60", "--volume-rate", "5"]
    codes: list[int] = []
    live = threading.Thread(target=lambda: codes.append(main(args)), daemon=True)
    live.start()
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:  # wait for the service to listen
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            break
        except OSError:
            time.sleep(0.1)
    assert main(["replay", str(folder / "sweep.seq.nrrd"), "--to", f"127.0.0.1:{port}", "--rate", "60"]) == 0
    live.join(timeout=60.0)
    assert codes == [0]
    printed = capsys.readouterr().out
    assert f"sent {N_FRAMES} frames" in printed and f"corrected {N_FRAMES} of {N_FRAMES} images" in printed
    assert np.array_equal(read_volume(volume).image, _offline_volume(record, folder / "model.json").image)


def _corrupt(message: Any) -> bytes:
    data = bytearray(message.pack())
    data[-1] ^= 0xFF  # the body no longer matches its CRC
    return bytes(data)


def test_faults_are_logged_and_the_service_goes_on(scan, tmp_path: Path, caplog) -> None:
    caplog.set_level(logging.INFO, logger="usdeform.live")
    sweep = scan["sweep"]
    pose_valid = np.ones(N_FRAMES, dtype=bool)
    pose_valid[5] = False  # tracking lost: PLUS Server does not send the transform
    sweep = dataclasses.replace(sweep, pose_valid=pose_valid)
    server, thread, out = serve(scan, record=tmp_path / "faults.seq.nrrd")
    viewer = LiveClient(("127.0.0.1", server.port))
    leaving = LiveClient(("127.0.0.1", server.port))
    # A malformed message (bad CRC), then bytes that are not OpenIGTLink at all.
    with socket.create_connection(("127.0.0.1", server.port)) as rogue:
        rogue.sendall(_corrupt(pyigtl.StringMessage("12.5", device_name="ContactForce")))
        rogue.sendall(struct.pack(">H12s20sIIQQ", 1, b"IMAGE", b"Image_Reference", 0, 0, 1 << 62, 0))
        time.sleep(0.3)
    # The scan source drops after 20 frames; another connection sends the rest.
    replay(sweep.select(slice(0, 20)), ("127.0.0.1", server.port), rate_hz=100.0)
    leaving.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    leaving.close()  # the viewer goes away without a goodbye (a reset)
    replay(sweep.select(slice(20, None)), ("127.0.0.1", server.port), rate_hz=100.0)
    thread.join(timeout=60.0)
    viewer.close()
    result = out["result"]
    assert result.images_read == N_FRAMES and result.frames_corrected == N_FRAMES - 1
    assert result.skipped == {"pose:ProbeToReference": 1} and result.malformed == 2
    logged = caplog.text
    assert "skipped image 5" in logged and "no TRANSFORM ProbeToReference matching it" in logged
    assert "skipped a malformed message" in logged and "CRC mismatch" in logged
    assert "dropped: 'IMAGE' message announces a body of 4611686018427387904 bytes" in logged
    assert viewer.named("CorrectedVolume")[-1].metadata["FramesInserted"] == str(N_FRAMES - 1)
    assert len(read_sequence(tmp_path / "faults.seq.nrrd")) == N_FRAMES - 1


def test_live_connects_to_a_plus_server(scan) -> None:
    port = free_port()
    source = threading.Thread(
        target=replay, args=(scan["sweep"], ("127.0.0.1", port)), kwargs={"rate_hz": 100.0, "listen": True}
    )
    source.start()
    _, thread, out = serve(scan, connect=("127.0.0.1", port))
    source.join(timeout=30.0)
    thread.join(timeout=60.0)
    assert out["result"].frames_corrected == N_FRAMES


def _transform(name: str, t: float, matrix: np.ndarray, status: str = "OK") -> Any:
    message = pyigtl.TransformMessage(matrix, timestamp=t, device_name=name)
    message.metadata = {"TransformStatus": status}
    return message


def _image(t: float, **metadata: str) -> Any:
    message = pyigtl.ImageMessage(np.zeros((1, 4, 6), np.uint8), timestamp=t, device_name="Image_Reference")
    message.metadata = metadata
    return message


def test_pairing_by_timestamp_with_the_image_delay_and_tracker_transforms() -> None:
    settings = StreamSettings(
        pose=("ProbeToTracker", "ReferenceToTracker"),
        force=ScalarSource.parse("META:ContactForce"),
        displacement=ScalarSource.parse("TRANSFORM:DisplacementToProbe:z"),
        image_delay_s=0.05,
    )
    pairer = Pairer(settings).with_calibration(np.eye(4))
    probe, reference, lift = np.eye(4), np.eye(4), np.eye(4)
    probe[:3, 3], reference[:3, 3], lift[2, 3] = (10.0, 0.0, 0.0), (0.0, 4.0, 0.0), 2.5
    for t in (0.90, 0.95, 1.00):
        pairer.add(_transform("ProbeToTracker", t, probe), 0.0)
        pairer.add(_transform("ReferenceToTracker", t, reference), 0.0)
        pairer.add(_transform("DisplacementToProbe", t, lift), 0.0)
    pairer.add(_image(1.0, ContactForce="7.5"), 0.0)  # shows the tissue at 0.95 s
    pairer.add(_image(1.05), 0.0)  # no force
    pairer.add(_image(1.2, ContactForce="7.5"), 0.0)  # no pose at 1.15 s: never guessed
    decided = list(pairer.ready(now=10.0))
    paired = decided[0]
    assert isinstance(paired, PairedFrame) and (paired.force, paired.displacement) == (7.5, 2.5)
    assert np.allclose(paired.probe_to_base[:3, 3], (10.0, -4.0, 0.0))
    assert [item[2] for item in decided[1:]] == ["force", "pose:ProbeToTracker"]


def test_pairing_waits_for_a_match_and_refuses_bad_sources() -> None:
    pairer = Pairer(StreamSettings(displacement=None, tolerance_s=0.01)).with_calibration(np.eye(4))
    pairer.add(_image(2.0), 0.0)
    pairer.add(_transform("ProbeToReference", 2.0, np.eye(4)), 0.0)
    assert list(pairer.ready(now=0.0)) == []  # the force may still come
    pairer.add(pyigtl.StringMessage("3.25", timestamp=2.005, device_name="ContactForce"), 0.0)
    assert list(pairer.ready(now=0.0)) == []  # a nearer force may still come
    pairer.add(pyigtl.StringMessage("3.5", timestamp=2.02, device_name="ContactForce"), 0.0)
    (paired,) = pairer.ready(now=0.0)
    assert isinstance(paired, PairedFrame) and paired.force == 3.25
    with pytest.raises(InputError, match="STRING:NAME, META:KEY or TRANSFORM:NAME:x"):
        ScalarSource.parse("STRING")
    with pytest.raises(InputError, match="model: expected a DisplacementModel or VesselAnchoredModel, got object"):
        LiveServer(object(), None)  # type: ignore[arg-type]


def test_the_image_delay_comes_from_a_diagnosis(tmp_path: Path) -> None:
    diagnosis = {"verdict": "explained", "named": ["force_sensor_error"], "effects": [{"effect": "force_sensor_error"}]}
    (tmp_path / "diagnosis.json").write_text(json.dumps(diagnosis))
    assert image_delay_from_diagnosis(tmp_path)[0] == 0.0
    (tmp_path / "diagnosis.json").write_text("{")
    with pytest.raises(FileFormatError, match=r"not a readable diagnosis\.json"):
        image_delay_from_diagnosis(tmp_path / "diagnosis.json")
