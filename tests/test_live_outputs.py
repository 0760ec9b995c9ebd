"""The live service's outputs off the frame-processing thread: the IMAGE bytes packed without copying
the voxels are pyigtl's, and the volume sent is built from the compounder on another thread while
frames are added, each volume holding whole batches."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from usdeform.live.connections import OUTBOX, Connections  # noqa: E402
from usdeform.live.engine import FrameStore, LiveVolume  # noqa: E402
from usdeform.live.pairing import PairedFrame  # noqa: E402
from usdeform.live.synthetic import synthetic_scan  # noqa: E402
from usdeform.live.transport import pack_message  # noqa: E402


@pytest.mark.parametrize("header_version", [1, 2])
@pytest.mark.parametrize(
    ("shape", "dtype"),
    [((3, 4, 5), np.float32), ((1, 7, 9), np.uint8), ((6,), np.uint8), ((2, 3), np.float32), ((2, 3, 4, 3), np.uint8)],
)
def test_packed_image_is_pyigtls(shape, dtype, header_version) -> None:
    rng = np.random.default_rng(len(shape))
    image = (rng.random(shape) * 200).astype(dtype)
    ijk_to_world = np.array([[0.5, 0, 0.1, 3], [0, 0.4, 0, -7.2], [0, 0, 0.3, 11.1], [0, 0, 0, 1]])
    message = pyigtl.ImageMessage(image, ijk_to_world_matrix=ijk_to_world, device_name="Volume", timestamp=1234.5678)
    message.header_version = header_version
    if header_version == 2:
        message.metadata = {"FramesInserted": "42", "Other": "x"}
    packed = b"".join(bytes(part) for part in pack_message(message))
    assert packed == message.pack()
    status = pyigtl.StringMessage("images 3", device_name="usdeformStatus")
    assert pack_message(status) == [status.pack()]


def test_volumes_built_on_another_thread_while_frames_are_added(tmp_path: Path) -> None:
    """Volumes taken from a second thread while batches are added (and the grid grows) come without an
    error, hold whole batches, never fewer frames than the one before, and the last is the whole scan's."""
    n_frames = 30
    model, sampled, sweep = synthetic_scan(n_frames)
    assert sweep.force is not None and sweep.probe_displacement is not None
    store = FrameStore(sweep.shape, sweep.image_to_probe, with_displacement=True, directory=tmp_path)
    live = LiveVolume(store, model, sampled, stiffness_source="sweep", margin_mm=0.5)
    taken: list[int] = []
    errors: list[BaseException] = []
    adding = threading.Event()

    def take() -> None:
        try:
            while adding.is_set() or not taken:
                sent = live.sent_volume()
                if sent is not None:
                    volume, frames = sent
                    assert volume.weight is not None and volume.image.shape == volume.weight.shape
                    taken.append(frames)
        except BaseException as error:
            errors.append(error)

    adding.set()
    reader = threading.Thread(target=take)
    reader.start()
    try:
        for start in range(0, n_frames, 3):
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
                for i in range(start, start + 3)
            ]
            live.add(store.append(frames))
        live.poll(wait=True)
        adding.clear()
        reader.join(timeout=30.0)
        last = live.sent_volume()
        whole = live.volume()
    finally:
        adding.clear()
        store.close()
    assert not reader.is_alive() and errors == []
    assert taken == sorted(taken) and all(frames % 3 == 0 for frames in taken)
    assert live.regrown >= 1
    assert last is not None and last[1] == n_frames and whole is not None
    assert np.array_equal(last[0].image, whole.image)


def test_outputs_offered_to_a_packing_thread_that_is_behind_are_refused_at_once() -> None:
    """The frame-processing thread never waits for the packing thread: with ``OUTBOX`` batches waiting, an
    offer is refused (the outputs come again at their next turn)."""
    connections = Connections(("127.0.0.1", 0), None, threading.Event(), pack=lambda output: [])
    assert all(connections.offer_outputs([number]) for number in range(OUTBOX))
    started = time.perf_counter()
    assert not connections.offer_outputs([OUTBOX])
    assert time.perf_counter() - started < 0.05
