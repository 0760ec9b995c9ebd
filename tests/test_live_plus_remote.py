"""PLUS Server's volume-reconstruction and recording commands, as Slicer's Plus Remote sends them to
``usdeform live``, and PLUS's replies, over loopback."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from live_helpers import N_FRAMES, plus_command, scan_fixture, serve  # noqa: E402
from usdeform.correction import correct_recording  # noqa: E402
from usdeform.io import read_sequence, read_volume  # noqa: E402
from usdeform.live import LiveClient, replay  # noqa: E402
from usdeform.live.plus_commands import CommandMessage, parse_command, reply_message  # noqa: E402
from usdeform.live.transport import receive_message  # noqa: E402
from usdeform.volume import VoxelGrid, compound_frames, corner_points  # noqa: E402

scan = scan_fixture("live-plus-remote")


def test_replies_are_plus_servers() -> None:
    message = CommandMessage("COMMAND", 7, "StartVolumeReconstruction", '<Command Name="StartVolumeReconstruction"/>')
    command = parse_command(message)
    assert command is not None and (command.name, command.command_id, command.v3) == (
        "StartVolumeReconstruction",
        7,
        True,
    )
    reply = reply_message(command, False, "Command failed. See error message.", 'x "in" progress')
    assert reply.content == (
        '<CommandReply Name="StartVolumeReconstruction" Status="FAIL" Error=\'x "in" progress\' '
        'Message="Command failed. See error message."></CommandReply>'
    )
    assert reply.metadata == {
        "Message": "Command failed. See error message.",
        "Status": "FAIL",
        "Error": 'x "in" progress',
    }
    # Packed and read back as OpenIGTLink bytes.
    import socket

    left, right = socket.socketpair()
    with left, right:
        left.sendall(reply.pack())
        read, _ = receive_message(right)
    assert (read.message_type, read.command_id, read.command_name, read.content) == (
        "RTS_COMMAND",
        7,
        "StartVolumeReconstruction",
        reply.content,
    )
    legacy = parse_command(pyigtl.StringMessage('<Command Name="SuspendVolumeReconstruction" />', device_name="CMD_12"))
    assert legacy is not None and (legacy.name, legacy.command_id, legacy.v3) == (
        "SuspendVolumeReconstruction",
        12,
        False,
    )
    ack = reply_message(legacy, True, "done")
    assert (ack.device_name, ack.string) == ("ACK_12", '<CommandReply Status="SUCCESS" Message="done" />')
    assert parse_command(pyigtl.StringMessage("12.5", device_name="ContactForce")) is None


def test_plus_remote_suspends_resumes_snapshots_and_stops_the_reconstruction(scan) -> None:
    sweep = scan["sweep"]
    server, thread, out = serve(scan, idle_stop_s=None)
    remote = LiveClient(("127.0.0.1", server.port), keep=100_000)
    reply = plus_command(remote, 1, '<Command Name="GetVolumeReconstructionSnapshot"/>')
    assert reply.metadata["Status"] == "FAIL" and "no frame was corrected" in reply.metadata["Error"]
    assert plus_command(remote, 2, '<Command Name="SuspendVolumeReconstruction"/>').metadata["Status"] == "SUCCESS"
    replay(sweep.select(slice(0, 20)), ("127.0.0.1", server.port), rate_hz=100.0)
    time.sleep(0.5)
    reply = plus_command(remote, 3, '<Command Name="ResumeVolumeReconstruction"/>')
    assert (
        reply.metadata["Message"]
        == "ResumeVolumeReconstruction(VolumeReconstructor) Volume reconstruction from live frames resumed."
    )
    reply = plus_command(remote, 4, '<Command Name="ResumeVolumeReconstruction"/>')
    assert reply.metadata["Status"] == "FAIL" and reply.metadata["Error"].endswith("is already in progress.")
    replay(sweep.select(slice(20, None)), ("127.0.0.1", server.port), rate_hz=100.0)
    time.sleep(0.5)
    reply = plus_command(remote, 5, '<Command Name="StartVolumeReconstruction" OutputSpacing="0.5 0.5 0.5"/>')
    assert reply.metadata["Error"].endswith("live volume reconstruction is in progress.")
    reply = plus_command(remote, 6, '<Command Name="GetVolumeReconstructionSnapshot" OutputVolDeviceName="Snap"/>')
    assert reply.metadata["Status"] == "SUCCESS"
    time.sleep(0.5)
    snapshots = remote.named("Snap")  # the volumes sent after it keep the name, as PLUS's device does
    assert snapshots and {snapshot.metadata["FramesInserted"] for snapshot in snapshots} == {"20"}
    reply = plus_command(remote, 7, '<Command Name="StopVolumeReconstruction" OutputVolDeviceName="Final"/>')
    assert reply.content.startswith('<CommandReply Name="StopVolumeReconstruction" Status="SUCCESS"')
    thread.join(timeout=30.0)
    remote.close()
    result = out["result"]
    assert result.frames_corrected == 20 and result.skipped == {"suspended": 20}
    assert remote.named("Final")[-1].metadata["FramesInserted"] == "20"


def _wait_for(server: Any, frames: int, seconds: float = 20.0) -> None:
    deadline = time.monotonic() + seconds
    while server.result.frames_corrected < frames:
        assert time.monotonic() < deadline, f"{server.result.frames_corrected} of {frames} frames corrected"
        time.sleep(0.02)


def test_plus_remote_records_the_frames_between_start_and_stop(scan, tmp_path: Path) -> None:
    """StartRecording, SuspendRecording, ResumeRecording and StopRecording with PLUS's replies; the file holds
    the frames taken in while recording."""
    sweep, base = scan["sweep"], "VirtualCapture (CaptureDevice) "
    server, thread, _ = serve(scan, idle_stop_s=None, output_dir=tmp_path)
    remote = LiveClient(("127.0.0.1", server.port), keep=100_000)
    reply = plus_command(remote, 1, '<Command Name="StopRecording"/>')
    assert reply.metadata["Error"] == base + "StopRecording Recording to file is already stopped."
    reply = plus_command(remote, 2, '<Command Name="StartRecording" OutputFilename="../scan.seq.nrrd"/>')
    assert reply.metadata["Error"] == base + "StartRecording Failed to open file ../scan.seq.nrrd."
    start = '<Command Name="StartRecording" CaptureDeviceId="CaptureDevice" OutputFilename="scan.seq.nrrd"/>'
    reply = plus_command(remote, 3, start)
    assert (reply.metadata["Status"], reply.metadata["Message"]) == ("SUCCESS", base + "StartRecording successful.")
    reply = plus_command(remote, 4, start)
    assert reply.metadata["Error"] == base + "StartRecording Recording to file is already in progress."
    to = ("127.0.0.1", server.port)
    replay(sweep.select(slice(0, 10)), to, rate_hz=100.0)
    _wait_for(server, 10)
    assert plus_command(remote, 5, '<Command Name="SuspendRecording"/>').metadata["Status"] == "SUCCESS"
    reply = plus_command(remote, 6, '<Command Name="SuspendRecording"/>')
    assert reply.metadata["Error"] == (
        base + "SuspendRecording Suspend recording failed: recording to file is not in progress."
    )
    replay(sweep.select(slice(10, 20)), to, rate_hz=100.0)
    _wait_for(server, 20)
    assert plus_command(remote, 7, '<Command Name="ResumeRecording"/>').metadata["Status"] == "SUCCESS"
    replay(sweep.select(slice(20, 30)), to, rate_hz=100.0)
    _wait_for(server, 30)
    reply = plus_command(remote, 8, '<Command Name="StopRecording"/>')
    path = tmp_path / "scan.seq.nrrd"
    assert reply.metadata["Message"] == base + f"StopRecording Recording 20 frames successful to file {path}"
    recorded = read_sequence(path)
    assert np.array_equal(recorded.frames, np.concatenate([sweep.frames[:10], sweep.frames[20:30]]))
    reply = plus_command(remote, 9, '<Command Name="ResumeRecording"/>')
    assert reply.metadata["Error"].endswith("Resume recording failed: recording to file was not started.")
    # A recording not stopped when the scan ends is written then.
    assert plus_command(remote, 10, '<Command Name="StartRecording" OutputFilename="end.mha"/>').metadata["Status"]
    replay(sweep.select(slice(30, 35)), to, rate_hz=100.0)
    _wait_for(server, 35)
    server.stop()
    thread.join(timeout=30.0)
    remote.close()
    assert np.array_equal(read_sequence(tmp_path / "end.mha").frames, sweep.frames[30:35])


def test_plus_remote_sets_the_output_grid_and_the_volume_file(scan, tmp_path: Path) -> None:
    """StartVolumeReconstruction's OutputSpacing, OutputOrigin and OutputExtent fix the grid (frames outside
    it left out); StopVolumeReconstruction's OutputVolFilename receives the final volume, which is the
    recording's corrected frames compounded on that grid."""
    corrected = correct_recording(scan["sweep"], scan["model"], scan["sampled"])
    corners = corner_points(corrected.image_to_base, (0, corrected.shape[1] - 1), (0, corrected.shape[0] - 1))
    lower, upper = corners.min(axis=0), corners.max(axis=0)
    spacing = np.array([0.5, 0.6, 0.7])
    counts = np.ceil((upper - lower) / spacing).astype(int)
    counts[np.argmax(upper - lower)] //= 2  # half the sweep is outside the grid
    origin = " ".join(f"{value:.3f}" for value in lower)
    extent = " ".join(f"0 {count}" for count in counts)
    record = tmp_path / "live.seq.nrrd"
    server, thread, out = serve(scan, idle_stop_s=None, output_dir=tmp_path, record=record)
    remote = LiveClient(("127.0.0.1", server.port), keep=100_000)
    bad = plus_command(remote, 1, f'<Command Name="StartVolumeReconstruction" OutputOrigin="{origin}"/>')
    assert bad.metadata["Status"] == "FAIL" and "give both" in bad.metadata["Error"]
    bad = plus_command(
        remote, 2, f'<Command Name="StartVolumeReconstruction" OutputOrigin="{origin}" OutputExtent="0 4 9 2 0 1"/>'
    )
    assert bad.metadata["Status"] == "FAIL" and "i0 <= i1" in bad.metadata["Error"]
    bad = plus_command(remote, 3, '<Command Name="StartVolumeReconstruction" OutputVolFilename="/tmp/v.nrrd"/>')
    assert bad.metadata["Error"].endswith("a file name without a directory is expected.")
    start = (
        f'<Command Name="StartVolumeReconstruction" OutputSpacing="0.5 0.6 0.7" OutputOrigin="{origin}" '
        f'OutputExtent="{extent}" OutputVolFilename="final.nrrd" OutputVolDeviceName="Final"/>'
    )
    assert plus_command(remote, 4, start).metadata["Status"] == "SUCCESS"
    replay(scan["sweep"], ("127.0.0.1", server.port), rate_hz=100.0)
    _wait_for(server, N_FRAMES)
    reply = plus_command(remote, 5, '<Command Name="StopVolumeReconstruction"/>')
    assert (reply.metadata["Status"], reply.metadata["Message"]) == ("SUCCESS", "Command succeeded.")
    thread.join(timeout=30.0)
    remote.close()
    assert out["result"].frames_corrected == N_FRAMES
    offline = correct_recording(read_sequence(record), scan["model"], scan["sampled"])
    origin_mm = np.array([float(value) for value in origin.split()])
    index_to_world = np.diag([*spacing, 1.0])
    index_to_world[:3, 3] = origin_mm
    grid = VoxelGrid((int(counts[2]) + 1, int(counts[1]) + 1, int(counts[0]) + 1), index_to_world)
    expected = compound_frames(offline.frames, offline.image_to_base, grid, valid=offline.pixel_valid)
    written = read_volume(tmp_path / "final.nrrd")
    assert written.image.shape == grid.shape and np.allclose(written.index_to_world, grid.index_to_world)
    assert np.array_equal(written.image, expected.image)
    assert np.array_equal(remote.named("Final")[-1].image, expected.image)
