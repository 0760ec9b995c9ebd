"""PLUS Server's volume-reconstruction commands, as Slicer's Plus Remote sends them to ``usdeform live``, and
PLUS's replies, over loopback."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

pyigtl = pytest.importorskip("pyigtl")

from usdeform.live import LiveClient, LiveServer, replay  # noqa: E402
from usdeform.live.plus_commands import CommandMessage, parse_command, reply_message  # noqa: E402
from usdeform.live.synthetic import synthetic_scan  # noqa: E402
from usdeform.live.transport import receive_message  # noqa: E402


def _command(client: LiveClient, command_id: int, xml: str) -> Any:
    """Send a COMMAND as Plus Remote does and wait for its RTS_COMMAND reply."""
    name = xml.split('Name="')[1].split('"')[0]
    client.connection.sendall(CommandMessage("COMMAND", command_id, name, xml, "PlusRemote").pack())
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        replies = [
            m for m in client.named("PlusRemote") if m.message_type == "RTS_COMMAND" and m.command_id == command_id
        ]
        if replies:
            return replies[0]
        time.sleep(0.01)
    raise AssertionError(f"no reply to {xml}")


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


def test_plus_remote_suspends_resumes_snapshots_and_stops_the_reconstruction() -> None:
    model, sampled, sweep = synthetic_scan(40)
    server = LiveServer(model, sampled, listen=("127.0.0.1", 0), max_seconds=60.0).start()
    out: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: out.setdefault("result", server.run()), daemon=True)
    thread.start()
    remote = LiveClient(("127.0.0.1", server.port), keep=100_000)
    reply = _command(remote, 1, '<Command Name="GetVolumeReconstructionSnapshot"/>')
    assert reply.metadata["Status"] == "FAIL" and "no frame was corrected" in reply.metadata["Error"]
    assert _command(remote, 2, '<Command Name="SuspendVolumeReconstruction"/>').metadata["Status"] == "SUCCESS"
    replay(sweep.select(slice(0, 20)), ("127.0.0.1", server.port), rate_hz=100.0)
    time.sleep(0.5)
    reply = _command(remote, 3, '<Command Name="ResumeVolumeReconstruction"/>')
    assert (
        reply.metadata["Message"]
        == "ResumeVolumeReconstruction(VolumeReconstructor) Volume reconstruction from live frames resumed."
    )
    reply = _command(remote, 4, '<Command Name="ResumeVolumeReconstruction"/>')
    assert reply.metadata["Status"] == "FAIL" and reply.metadata["Error"].endswith("is already in progress.")
    replay(sweep.select(slice(20, None)), ("127.0.0.1", server.port), rate_hz=100.0)
    time.sleep(0.5)
    reply = _command(remote, 5, '<Command Name="StartVolumeReconstruction" OutputSpacing="0.5 0.5 0.5"/>')
    assert reply.metadata["Error"].endswith("live volume reconstruction is in progress.")
    reply = _command(remote, 6, '<Command Name="GetVolumeReconstructionSnapshot" OutputVolDeviceName="Snap"/>')
    assert reply.metadata["Status"] == "SUCCESS"
    time.sleep(0.5)
    snapshots = remote.named("Snap")  # the volumes sent after it keep the name, as PLUS's device does
    assert snapshots and {snapshot.metadata["FramesInserted"] for snapshot in snapshots} == {"20"}
    reply = _command(remote, 7, '<Command Name="StopVolumeReconstruction" OutputVolDeviceName="Final"/>')
    assert reply.content.startswith('<CommandReply Name="StopVolumeReconstruction" Status="SUCCESS"')
    thread.join(timeout=30.0)
    remote.close()
    result = out["result"]
    assert result.frames_corrected == 20 and result.skipped == {"suspended": 20}
    assert remote.named("Final")[-1].metadata["FramesInserted"] == "20"
