"""The live service's memory does not grow with the scan: the frame store keeps every frame's pixels and
fields in files (none in memory) and gives them back exactly; the pairer counts unusable messages by kind,
not by content. A client timing every message keeps no object per message."""

from __future__ import annotations

import gc
import socket
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from usdeform.live import LiveClient  # noqa: E402
from usdeform.live.engine import FrameStore  # noqa: E402
from usdeform.live.pairing import PairedFrame, Pairer, StreamSettings  # noqa: E402

SHAPE = (16, 12)


def _pose(rng: np.random.Generator) -> np.ndarray:
    """A random rigid transform, (4, 4) mm."""
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pose = np.eye(4)
    pose[:3, :3] = rotation * np.sign(np.linalg.det(rotation))
    pose[:3, 3] = rng.normal(scale=50.0, size=3)
    return pose


def _frames(rng: np.random.Generator, first: int, n: int) -> list[PairedFrame]:
    return [
        PairedFrame(
            index,
            1000.0 + index / 30 + float(rng.random()) * 1e-9,
            rng.integers(0, 256, SHAPE, dtype=np.uint8),
            _pose(rng),
            float(rng.normal()),
            float(rng.normal()),
            0.0,
        )
        for index in range(first, first + n)
    ]


def test_frame_store_gives_back_every_field_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    store = FrameStore(SHAPE, np.diag([0.1, 0.1, 1.0, 1.0]), with_displacement=True, directory=tmp_path)
    kept: list[PairedFrame] = []
    try:
        for n in (1, 7, 3, 12):
            frames = _frames(rng, len(kept), n)
            batch = store.append(frames)
            assert np.array_equal(batch.timestamps, [frame.timestamp for frame in frames])
            kept += frames
        assert len(store) == len(kept) == 23
        part = store.recording(4, 15)
        expected = kept[4:15]
        assert np.array_equal(part.frames, [frame.pixels for frame in expected])
        assert np.array_equal(part.timestamps, [frame.timestamp for frame in expected])
        assert np.array_equal(part.probe_to_base, [frame.probe_to_base for frame in expected])
        assert np.array_equal(part.force, [frame.force for frame in expected])
        assert part.probe_displacement is not None
        assert np.array_equal(part.probe_displacement, [frame.displacement for frame in expected])
        assert len(store.recording()) == 23
    finally:
        store.close()


def test_frame_store_memory_does_not_grow_with_the_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    store = FrameStore(SHAPE, np.eye(4), with_displacement=False, directory=tmp_path)
    batches = [_frames(rng, 10 * number, 10) for number in range(100)]
    tracemalloc.start()
    try:
        for batch in batches[:10]:
            store.append(batch)
        before = tracemalloc.get_traced_memory()[0]
        for batch in batches[10:]:
            store.append(batch)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
        store.close()
    # 900 frames more: fields kept per frame in memory would be about 350 bytes a frame (310 kB here).
    assert grown < 20_000, f"{grown} bytes more after 900 more frames"


def test_pairer_counts_unusable_strings_by_stream_not_by_text() -> None:
    pairer = Pairer(StreamSettings())
    notes = [
        pairer.add(pyigtl.StringMessage(f"force={i} N", timestamp=float(i), device_name="ContactForce"), 0.0)
        for i in range(50)
    ]
    assert notes[0] == "ignoring STRING 'ContactForce' without a number (e.g. 'force=0 N')"
    assert notes[1:] == [None] * 49
    assert dict(pairer.ignored) == {"STRING 'ContactForce' without a number": 50}


def test_a_timing_client_keeps_every_arrival_and_no_object_per_message() -> None:
    """The times of all 3000 messages are kept, the messages only up to ``keep``: the objects the garbage
    collector tracks (whose full collections pause the client's reading) do not grow with the messages."""
    stamps = 1000.0 + np.arange(3000) / 30
    data = b"".join(
        pyigtl.TransformMessage(np.eye(4), timestamp=t, device_name="ProbeToReference").pack() for t in stamps
    )
    with socket.create_server(("127.0.0.1", 0)) as listener:
        gc.collect()
        tracked = len(gc.get_objects())
        client = LiveClient(listener.getsockname(), keep=10, timing=True, max_seconds=30.0)
        connection, _ = listener.accept()
        with connection:
            connection.sendall(data)
        client._thread.join(timeout=30.0)
        gc.collect()
        grown = len(gc.get_objects()) - tracked
        client.close()
    assert client.counts == {"ProbeToReference": 3000}
    assert len(client.messages) == 10 and client.messages[-1][1].timestamp == pytest.approx(stamps[-1])
    assert np.allclose(client.timestamps["ProbeToReference"], stamps, rtol=0, atol=1e-6)
    arrivals = np.array(client.arrivals["ProbeToReference"])
    assert len(arrivals) == 3000 and np.all(np.diff(arrivals) >= 0)
    # The 3000 messages kept would be over 6000 objects (each message and its metadata dict).
    assert grown < 1000, f"{grown} objects more after 3000 messages"
