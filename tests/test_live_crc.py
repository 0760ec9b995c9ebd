"""The OpenIGTLink CRC-64 of the Rust core (``_core.crc64``, which the live service's ``transport.crc64``
calls) against its plain-Python twin (``usdeform.reference.crc64``) and pyigtl's own ``CRC64`` on random
bytes, the empty input and lengths that are not multiples of 8; its bad inputs; and the interpreter lock
released while it runs."""

from __future__ import annotations

import sys
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usdeform import _core, reference
from usdeform.errors import InputError

pyigtl = pytest.importorskip("pyigtl")

from usdeform.live.transport import crc64  # noqa: E402

SETTINGS = settings(max_examples=200, deadline=None)
CRCS = st.integers(0, 2**64 - 1)


def _core_crc(data: bytes, crc: int = 0) -> int:
    return _core.crc64(np.frombuffer(data, dtype=np.uint8), crc)


@SETTINGS
@given(data=st.binary(max_size=3000), crc=CRCS)
def test_crc_matches_the_reference_and_pyigtl(data: bytes, crc: int) -> None:
    expected = int(pyigtl.messages.CRC64(data, crc))
    assert _core_crc(data, crc) == expected
    assert reference.crc64(data, crc) == expected
    assert crc64(data, crc) == expected


@pytest.mark.parametrize("length", [0, 1, 3, 7, 8, 9, 15, 16, 17, 31, 33, 255, 1001])
def test_crc_of_short_and_odd_lengths(length: int) -> None:
    data = np.random.default_rng(length).integers(0, 256, length, dtype=np.uint8).tobytes()
    assert _core_crc(data) == reference.crc64(data) == int(pyigtl.messages.CRC64(data))


def test_crc_check_value_and_empty_input() -> None:
    assert _core_crc(b"123456789") == 0x6C40DF5F0B497347  # CRC-64/ECMA-182's catalogued check value
    assert _core_crc(b"") == 0
    assert _core_crc(b"", 2**64 - 1) == 2**64 - 1  # no byte: the CRC so far, unchanged


@SETTINGS
@given(data=st.binary(max_size=600), split=st.integers(0, 600))
def test_crc_continues_across_parts(data: bytes, split: int) -> None:
    first = _core_crc(data[:split])
    assert _core_crc(data[split:], first) == _core_crc(data)


def test_crc_of_a_volume_view_is_pyigtls() -> None:
    volume = np.random.default_rng(7).random((9, 31, 17), dtype=np.float32)
    view = volume.data.cast("B")
    assert crc64(view) == int(pyigtl.messages.CRC64(volume.tobytes()))
    assert crc64(memoryview(b"")) == 0


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"abc", "data: expected a numpy array"),
        (np.zeros(4, np.int16), "data: expected dtype"),
        (np.zeros((2, 2), np.uint8), "data: expected shape"),
        (np.zeros(8, np.uint8)[::2], "data: expected a C-contiguous array"),
    ],
)
def test_crc_bad_inputs_are_input_errors(data: object, message: str) -> None:
    with pytest.raises(InputError, match=message):
        _core.crc64(data)  # type: ignore[arg-type]


def test_crc_releases_the_interpreter_lock() -> None:
    """With a switch interval far longer than the test, another thread can run during the call only if
    the call releases the lock; tried a few times, as that thread must also be scheduled in time."""
    data = np.random.default_rng(3).integers(0, 256, 1 << 25, dtype=np.uint8)
    interval = sys.getswitchinterval()
    try:
        for _ in range(10):
            gate, ran = threading.Event(), threading.Event()
            other = threading.Thread(target=lambda gate=gate, ran=ran: gate.wait() and ran.set())
            other.start()
            sys.setswitchinterval(1000.0)
            gate.set()
            _core.crc64(data)
            released = ran.is_set()
            sys.setswitchinterval(interval)
            other.join()
            if released:
                return
        pytest.fail("no other thread ran during ten CRCs of 32 MiB")
    finally:
        sys.setswitchinterval(interval)
