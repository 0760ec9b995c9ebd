"""The live service with more than one connection, over loopback: a stray sender or a second replay
does not make the scan's frames late; a viewer that does not read holds up no other; frames go ahead of
volumes; each frame goes out
as soon as it is corrected, with the frame as received and both poses; SIGTERM ends a scan as Ctrl-C does;
``replay --serve`` serves several clients."""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from live_helpers import N_FRAMES, free_port, scan_fixture, serve  # noqa: E402
from usdeform.correction import correct_recording  # noqa: E402
from usdeform.io import read_sequence, read_volume  # noqa: E402
from usdeform.live import LiveClient, OutputSettings, StreamSettings, replay  # noqa: E402
from usdeform.live.connections import ViewerQueue  # noqa: E402
from usdeform.live.pairing import Pairer  # noqa: E402
from usdeform.live.replay import replay_messages  # noqa: E402

scan = scan_fixture("live-network")


def test_a_stray_image_and_a_second_replay_do_not_make_the_scan_late(scan, caplog) -> None:
    """An IMAGE stamped with the wall clock (pyigtl's default) from another connection, then the same
    recording replayed twice: every frame of both replays is corrected; the stray image alone is skipped."""
    caplog.set_level(logging.INFO, logger="usdeform.live")
    server, thread, out = serve(scan)
    with socket.create_connection(("127.0.0.1", server.port)) as stray:
        image = np.zeros(scan["model"].frame_shape, np.uint8)[np.newaxis]
        stray.sendall(pyigtl.ImageMessage(image, device_name="Image_Reference").pack())
        time.sleep(0.1)
        # The scan on the recording's clock, far before the stray image's; then again, as PLUS stamps it.
        replay(scan["sweep"], ("127.0.0.1", server.port), rate_hz=100.0, clock="recording")
        replay(scan["sweep"], ("127.0.0.1", server.port), rate_hz=100.0, clock="wall")
    thread.join(timeout=60.0)
    result = out["result"]
    assert (result.images_read, result.frames_corrected) == (2 * N_FRAMES + 1, 2 * N_FRAMES)
    assert sum(result.skipped.values()) == 1 and "order" not in result.skipped
    assert "stamped at or before" not in caplog.text


def test_skips_are_logged_the_first_and_every_hundredth() -> None:
    pairer = Pairer(StreamSettings()).with_calibration(np.eye(4))
    image = pyigtl.ImageMessage(np.zeros((1, 4, 6), np.uint8), timestamp=5.0, device_name="Image_Reference")
    notes = [pairer.add(image, 0.0, "a") for _ in range(250)]
    logged = [number for number, note in enumerate(notes) if note]
    assert logged == [1, 100, 200]  # the 1st, 100th and 200th image out of order (the first is in order)
    assert pairer.skipped["order"] == 249
    assert "(100 skipped for this so far)" in str(notes[100])
    assert pairer.add(image, 0.0, "b") is None  # another connection keeps its own order


def _send_split(
    sweep: Any, scan_socket: socket.socket, robot_socket: socket.socket, rate_hz: float, loops: int
) -> None:
    """The recording as PLUS Server sends it on ``scan_socket``, but its ContactForce on ``robot_socket``
    (a robot node), ``loops`` times with ever later timestamps."""
    period = float(sweep.timestamps[-1] - sweep.timestamps[0]) + float(np.median(np.diff(sweep.timestamps)))
    start = time.perf_counter()
    for count in range(loops * len(sweep)):
        loop, frame = divmod(count, len(sweep))
        time.sleep(max(0.0, start + count / rate_hz - time.perf_counter()))
        messages = replay_messages(sweep, frame, float(sweep.timestamps[frame] + loop * period))
        robot_socket.sendall(b"".join(m.pack() for m in messages if m.device_name == "ContactForce"))
        scan_socket.sendall(b"".join(m.pack() for m in messages if m.device_name != "ContactForce"))


def test_a_viewer_that_does_not_read_holds_up_no_other_and_keeps_its_input(scan, caplog) -> None:
    """A robot node sends the force and never reads what it is sent: once its queue is full it gets no more
    outputs, but its force is still read; a viewer that reads gets every corrected frame without a stall."""
    caplog.set_level(logging.INFO, logger="usdeform.live")
    loops = 5
    server, thread, out = serve(scan, outputs=OutputSettings(volume_rate_hz=10.0))
    good = LiveClient(("127.0.0.1", server.port), keep=10_000, keep_pixels=False)
    robot = socket.socket()
    robot.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    robot.connect(("127.0.0.1", server.port))
    with socket.create_connection(("127.0.0.1", server.port)) as source:
        _send_split(scan["sweep"], source, robot, rate_hz=200.0, loops=loops)
        thread.join(timeout=60.0)
    robot.close()
    good.close()
    result = out["result"]
    assert result.frames_corrected == loops * N_FRAMES
    assert "gets no more outputs; its messages are still read" in caplog.text
    arrivals = [t for t, m in good.messages if m.device_name == "CorrectedImage"]
    assert len(arrivals) == loops * N_FRAMES
    assert max(np.diff(arrivals)) < 1.0  # the old shared sending thread froze it for 5 s


def test_each_frame_goes_out_when_corrected_with_the_raw_frame_and_both_poses(scan) -> None:
    """At 10 frames/s each corrected frame reaches a separate client well within a frame period of its
    sending (not when the next frame comes), with the frame as received and both poses."""
    server, thread, out = serve(scan, outputs=OutputSettings(volume_rate_hz=2.0))
    client = LiveClient(("127.0.0.1", server.port), keep=10_000)
    sent = replay(scan["sweep"].select(slice(0, 20)), ("127.0.0.1", server.port), rate_hz=10.0)
    thread.join(timeout=60.0)
    client.close()
    assert out["result"].frames_corrected == 20
    received = {m.timestamp: t for t, m in client.messages if m.device_name == "CorrectedImage"}
    received_stamps = sorted(received)
    assert len(received) == 20
    latency = [received[t] - sent.sent_at[i] for i, t in enumerate(sorted(received))]
    assert np.median(latency) < 0.05, latency
    for name in ("Image_Reference", "ProbeToReference", "CorrectedProbe"):
        assert len(client.named(name)) == 20, name
    # The relayed frame is the frame as received; the corrected pose is the probe pose at zero force.
    sweep = scan["sweep"]
    assert np.array_equal(client.named("Image_Reference")[3].image[0], sweep.frames[3])
    corrected = correct_recording(sweep.select(slice(0, 20)), scan["model"], scan["sampled"])
    pose = corrected.image_to_base[3] @ np.linalg.inv(sweep.image_to_probe)
    assert np.allclose(client.named("CorrectedProbe")[3].matrix, pose, atol=1e-3)
    assert np.allclose(client.named("ProbeToReference")[3].matrix, sweep.probe_to_base[3], atol=1e-3)
    # Idle, nothing is sent again: one volume per change, the last holding every frame.
    volumes = client.named("CorrectedVolume")
    inserted = [int(v.metadata["FramesInserted"]) for v in volumes]
    assert inserted[:-1] == sorted(set(inserted[:-1])) and inserted[-1] == 20
    assert volumes[-1].timestamp == received_stamps[19]  # the input's clock


def _wait_for_port(port: int, seconds: float = 120.0, process: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and (process is None or process.poll() is None):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"nothing listens on {port}")


def test_sigterm_ends_the_scan_as_ctrl_c(scan, tmp_path: Path) -> None:
    """``kill`` mid-scan: exit 0, the recording and the volume written, the volume that of ``usdeform correct``
    on the recording, voxel for voxel."""
    folder, port = scan["folder"], free_port()
    record, volume = tmp_path / "scan.seq.nrrd", tmp_path / "scan.nrrd"
    argv = ["live", "--model", str(folder / "model.json"), "--listen", f"127.0.0.1:{port}"]
    argv += ["--record", str(record), "--volume", str(volume), "--max-seconds", "120"]
    code = "import sys; from usdeform.cli import main; sys.exit(main(sys.argv[1:]))"
    live = subprocess.Popen([sys.executable, "-c", code, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _wait_for_port(port, process=live)
        replay(scan["sweep"].select(slice(0, 30)), ("127.0.0.1", port), rate_hz=100.0)
        os.kill(live.pid, signal.SIGTERM)
        stdout, stderr = live.communicate(timeout=60)
    finally:
        live.kill()
    assert live.returncode == 0, stderr.decode()
    assert "corrected 30 of 30 images" in stdout.decode() and b"terminated" in stderr
    assert len(read_sequence(record)) == 30
    offline = tmp_path / "offline.nrrd"
    redo = ["correct", str(record), "--model", str(folder / "model.json"), "--output", str(tmp_path / "c.seq.nrrd")]
    subprocess.run([sys.executable, "-c", code, *redo, "--volume", str(offline)], check=True, capture_output=True)
    assert np.array_equal(read_volume(volume).image, read_volume(offline).image)


def test_live_refuses_nothing_corrected_with_files_asked_for_and_a_missing_output_dir(
    scan, tmp_path: Path, capsys
) -> None:
    from usdeform.cli import main

    record = tmp_path / "none.seq.nrrd"
    argv = ["live", "--model", str(scan["folder"] / "model.json"), "--listen", "127.0.0.1:0"]
    assert main([*argv, "--record", str(record), "--max-seconds", "0.3"]) == 2
    assert f"no frame was corrected (0 images read): {record} not written" in capsys.readouterr().err
    assert not record.exists()
    missing = tmp_path / "missing"
    assert main([*argv, "--output-dir", str(missing), "--max-seconds", "0.3"]) == 2
    assert f"output_dir {missing}: not a directory" in capsys.readouterr().err


def test_replay_serves_several_clients(scan) -> None:
    port = free_port()
    result: dict[str, Any] = {}
    source = threading.Thread(
        target=lambda: result.setdefault(
            "replay", replay(scan["sweep"], ("127.0.0.1", port), rate_hz=50.0, listen=True, timeout_s=20.0)
        )
    )
    source.start()
    _wait_for_port(port)
    clients = [LiveClient(("127.0.0.1", port), keep=1000) for _ in range(3)]
    source.join(timeout=60.0)
    time.sleep(0.2)
    for client in clients:
        client.close()
    assert result["replay"].clients >= 3  # the port check's connection may count too
    counts = [len(client.named("Image_Reference")) for client in clients]
    assert all(count >= N_FRAMES - 5 for count in counts), counts  # each from its arrival on
    assert len({client.named("Image_Reference")[-1].timestamp for client in clients}) == 1  # the same last frame


def test_a_viewer_queue_sends_frames_first_and_a_volume_right_after_a_frame() -> None:
    """Frames overtake a volume waiting; while frames flow (every 50 ms), a volume queued between two frames
    goes right after the next one; once frames stopped, it goes after twice their interval."""
    outputs = ViewerQueue(16)
    taken: list[tuple[float, bytes]] = []

    def send() -> None:  # as a viewer's sending thread
        while (data := outputs.get()) is not None:
            taken.append((time.perf_counter(), bytes(data[0])))

    sender = threading.Thread(target=send)
    outputs.put([b"v0"])
    outputs.put([b"f0"], ahead=True)
    sender.start()
    for index in range(1, 5):
        time.sleep(0.05)
        if index == 3:
            outputs.put([b"v1"])
            time.sleep(0.01)
        outputs.put([f"f{index}".encode()], ahead=True)
    time.sleep(0.05)
    stopped = time.perf_counter()
    outputs.put([b"v2"])
    outputs.put(None)
    sender.join(timeout=5.0)
    order = [name for _, name in taken]
    assert order == [b"f0", b"v0", b"f1", b"f2", b"f3", b"v1", b"f4", b"v2"]
    waited = taken[-1][0] - stopped
    assert 0.05 < waited < 0.5  # twice the frames' interval (about 0.1 s) after the last frame
