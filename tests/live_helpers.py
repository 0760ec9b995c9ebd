"""What the live service's tests share: a synthetic scan with its model and sequence files, a service
running in a thread on a free loopback port, a free port, and a Plus Remote command and its reply."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from usdeform.io import save_model, write_sequence
from usdeform.live import LiveClient, LiveServer
from usdeform.live.plus_commands import CommandMessage
from usdeform.live.synthetic import synthetic_scan

#: Frames of the synthetic sweep (96 x 96 pixels).
N_FRAMES = 40


def scan_fixture(name: str) -> Callable[..., dict[str, Any]]:
    """A module fixture ``scan``: a 40-frame synthetic sweep of 96 x 96 frames, its model and the files
    ``model.json`` and ``sweep.seq.nrrd`` in a folder named after ``name``."""

    @pytest.fixture(scope="module")
    def scan(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
        folder: Path = tmp_path_factory.mktemp(name)
        model, sampled, sweep = synthetic_scan(N_FRAMES)
        save_model(folder / "model.json", model, sampled)
        write_sequence(folder / "sweep.seq.nrrd", sweep)
        return {"folder": folder, "model": model, "sampled": sampled, "sweep": sweep}

    return scan


def serve(scan: dict[str, Any], **options: Any) -> tuple[LiveServer, threading.Thread, dict[str, Any]]:
    """A live server on a free loopback port, running in a thread until it has had no message for 1 s
    (``idle_stop_s``) or 60 s passed; its result is ``out["result"]`` once the thread ended."""
    options.setdefault("idle_stop_s", 1.0)
    options.setdefault("max_seconds", 60.0)
    server = LiveServer(scan["model"], scan["sampled"], listen=("127.0.0.1", 0), **options).start()
    out: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: out.setdefault("result", server.run()), daemon=True)
    thread.start()
    return server, thread, out


def free_port() -> int:
    """A loopback port free when asked."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def plus_command(client: LiveClient, command_id: int, xml: str, seconds: float = 10.0) -> Any:
    """Send a COMMAND as Plus Remote does and wait for its RTS_COMMAND reply."""
    name = xml.split('Name="')[1].split('"')[0]
    client.connection.sendall(CommandMessage("COMMAND", command_id, name, xml, "PlusRemote").pack())
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        replies = [
            m for m in client.named("PlusRemote") if m.message_type == "RTS_COMMAND" and m.command_id == command_id
        ]
        if replies:
            return replies[0]
        time.sleep(0.01)
    raise AssertionError(f"no reply to {xml}")
