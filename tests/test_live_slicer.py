"""Where 3D Slicer places what ``usdeform live`` sends, against Slicer's own code.

Slicer's OpenIGTLinkIF turns an IMAGE into a volume node whose IJKToRAS is OpenIGTLinkIO's
``ImageConverter::IGTLToVTKTransform`` of the message (SlicerOpenIGTLink's ``vtkMRMLIGTLConnectorNode`` sets
it with ``SetIJKToRASMatrix``); the coordinate flag is never read. :func:`igtlio_ijk_to_ras` is a Python
twin of that conversion, applied to the bytes the service sends. A saved volume file is placed by Slicer's
``vtkMRMLVolumeArchetypeStorageNode`` (from the ``slicer-core`` package: the ``slicer`` extra; those tests
skip without it). Placement ``plus``: the corrected stream lands where PLUS Server's raw stream lands;
placement ``files``: where the saved volume files land.
"""

from __future__ import annotations

import socket
import struct
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pyigtl = pytest.importorskip("pyigtl")

from live_helpers import serve  # noqa: E402
from usdeform.correction import correct_recording  # noqa: E402
from usdeform.io import read_volume, save_model, write_sequence  # noqa: E402
from usdeform.live import OutputSettings, replay  # noqa: E402
from usdeform.live.replay import replay_messages  # noqa: E402
from usdeform.live.synthetic import synthetic_scan  # noqa: E402
from usdeform.live.transport import pack_message  # noqa: E402

N_FRAMES = 30
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def igtlio_ijk_to_ras(body: bytes, header_version: int = 2) -> tuple[np.ndarray, int]:
    """The IJKToRAS Slicer gives the volume of an IMAGE message body, and the body's coordinate flag
    (1 RAS, 2 LPS): libigtl's ``igtl_image_get_matrix`` (spacing = the lengths of the matrix's columns,
    which it normalises) then OpenIGTLinkIO's ``IGTLToVTKTransform`` (columns times spacing; the origin
    moved from the image's centre, OpenIGTLink's, to its first voxel, VTK's), in float32 as they compute."""
    offset = struct.unpack(">H", body[:2])[0] if header_version > 1 else 0  # the extended header's size
    fields = struct.unpack(">H B B B B 3H 12f 3H 3H", body[offset : offset + 72])
    coordinate, size = fields[4], np.array(fields[5:8])
    matrix = np.array(fields[8:20], dtype=np.float32)
    columns = [matrix[0:3], matrix[3:6], matrix[6:9]]
    spacing = [np.float32(np.sqrt(np.sum(c * c, dtype=np.float32))) for c in columns]
    normals = [c / s for c, s in zip(columns, spacing, strict=True)]  # igtl_image_get_matrix
    ijk_to_ras = np.eye(4)
    centre_shift = np.zeros(3, dtype=np.float32)
    for axis, (normal, step) in enumerate(zip(normals, spacing, strict=True)):
        length = np.float32(np.sqrt(np.sum(normal * normal, dtype=np.float32)))
        unit = normal / length
        half_fov = np.float32(step * length * (size[axis] - 1) / 2.0)
        centre_shift += unit * half_fov
        ijk_to_ras[:3, axis] = unit * step
    ijk_to_ras[:3, 3] = matrix[9:12] - centre_shift
    return ijk_to_ras, coordinate


class RawClient:
    """A viewer that keeps the bytes of each message: ``(type, device name, body)``."""

    def __init__(self, port: int) -> None:
        self.connection = socket.create_connection(("127.0.0.1", port), timeout=30.0)
        self.messages: list[tuple[str, str, bytes]] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _exact(self, size: int) -> bytes:
        data = b""
        while len(data) < size:
            chunk = self.connection.recv(size - len(data))
            if not chunk:
                raise EOFError
            data += chunk
        return data

    def _read(self) -> None:
        try:
            while True:
                header = struct.unpack(">H12s20sIIQQ", self._exact(58))
                kind, name = (part.rstrip(b"\0").decode() for part in header[1:3])
                self.messages.append((kind, name, self._exact(header[5])))
        except (EOFError, OSError):
            return

    def bodies(self, name: str) -> list[bytes]:
        return [body for _, device, body in self.messages if device == name]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Any]:
    """One live scan per placement, each with its volume file and what a viewer received, byte for byte."""
    folder = tmp_path_factory.mktemp("live-slicer")
    model, sampled, sweep = synthetic_scan(N_FRAMES)
    save_model(folder / "model.json", model, sampled)
    write_sequence(folder / "sweep.seq.nrrd", sweep)
    runs: dict[str, Any] = {"sweep": sweep, "model": model, "sampled": sampled}
    for placement in ("plus", "files"):
        server, thread, out = serve(
            runs,
            outputs=OutputSettings(placement=placement),  # type: ignore[arg-type]
            volume_path=folder / f"{placement}.nrrd",
        )
        client = RawClient(server.port)
        replay(sweep, ("127.0.0.1", server.port), rate_hz=100.0)
        thread.join(timeout=60.0)
        client.thread.join(timeout=10.0)
        assert out["result"].frames_corrected == N_FRAMES
        runs[placement] = {"client": client, "volume": folder / f"{placement}.nrrd"}
    return runs


def _plus_image_to_ras(sweep: Any, frame: int) -> np.ndarray:
    """Where Slicer puts PLUS Server's raw frame (as ``usdeform replay`` sends it, as PLUS does)."""
    image = next(m for m in replay_messages(sweep, frame, float(sweep.timestamps[frame])) if m.message_type == "IMAGE")
    packed = b"".join(bytes(part) for part in pack_message(image))
    return igtlio_ijk_to_ras(packed[58:])[0]


def test_the_twin_reads_back_what_pyigtl_writes() -> None:
    """The twin on pyigtl's own IMAGE: a volume placed by its first voxel's centre, as VTK places it."""
    index_to_world = np.array([[0.5, 0, 0, 3.0], [0, 0, -0.4, 7.5], [0, 0.3, 0, -2.0], [0, 0, 0, 1]])
    message = pyigtl.ImageMessage(np.zeros((4, 5, 6), np.float32), ijk_to_world_matrix=index_to_world)
    for version in (1, 2):
        message.header_version = version
        ijk_to_ras, flag = igtlio_ijk_to_ras(message.pack()[58:], version)
        assert np.allclose(ijk_to_ras, index_to_world, atol=1e-5) and flag == 2  # pyigtl's default: LPS


@pytest.mark.parametrize("placement", ["plus", "files"])
def test_every_image_sent_says_ras(runs, placement) -> None:
    client = runs[placement]["client"]
    for name in ("CorrectedVolume", "CorrectedImage", "Image_Reference"):
        assert client.bodies(name), name
        assert {igtlio_ijk_to_ras(body)[1] for body in client.bodies(name)} == {1}, name


def test_plus_placement_overlays_plus_servers_raw_stream(runs) -> None:
    """The frames relayed land in Slicer exactly where PLUS Server's raw frames land, and each corrected frame
    at its zero-force pose in the same frame of reference."""
    sweep, client = runs["sweep"], runs["plus"]["client"]
    corrected = correct_recording(sweep, runs["model"], runs["sampled"])
    for frame in (0, 11, N_FRAMES - 1):
        raw = igtlio_ijk_to_ras(client.bodies("Image_Reference")[frame])[0]
        assert np.allclose(raw, _plus_image_to_ras(sweep, frame), atol=1e-4)
        shown = igtlio_ijk_to_ras(client.bodies("CorrectedImage")[frame])[0]
        assert np.allclose(shown, corrected.image_to_base[frame], atol=1e-3)
    volume = read_volume(runs["plus"]["volume"])
    assert np.allclose(igtlio_ijk_to_ras(client.bodies("CorrectedVolume")[-1])[0], volume.index_to_world, atol=1e-4)


def test_files_placement_turns_lps_to_ras(runs) -> None:
    client = runs["files"]["client"]
    volume = read_volume(runs["files"]["volume"])
    shown = igtlio_ijk_to_ras(client.bodies("CorrectedVolume")[-1])[0]
    assert np.allclose(shown, LPS_TO_RAS @ volume.index_to_world, atol=1e-4)
    raw_plus = igtlio_ijk_to_ras(runs["plus"]["client"].bodies("Image_Reference")[3])[0]
    raw_files = igtlio_ijk_to_ras(client.bodies("Image_Reference")[3])[0]
    assert np.allclose(raw_files, LPS_TO_RAS @ raw_plus, atol=1e-4)


def _slicer_ijk_to_ras(path: Path) -> np.ndarray:
    """The IJKToRAS Slicer gives a volume file it loads (``vtkMRMLVolumeArchetypeStorageNode``)."""
    slicer_core = pytest.importorskip("slicer_core", reason="Slicer's MRML needs the 'slicer' extra (slicer-core)")
    import vtk

    scene = slicer_core.vtkMRMLScene()
    node = slicer_core.vtkMRMLScalarVolumeNode()
    scene.AddNode(node)
    storage = slicer_core.vtkMRMLVolumeArchetypeStorageNode()
    scene.AddNode(storage)
    storage.SetFileName(str(path))
    assert storage.ReadData(node) == 1, path
    matrix = vtk.vtkMatrix4x4()
    node.GetIJKToRASMatrix(matrix)
    return np.array([[matrix.GetElement(row, col) for col in range(4)] for row in range(4)])


def test_slicer_places_the_files_stream_on_the_saved_volume(runs) -> None:
    """Slicer's own reader: the saved volume (0.5 mm voxels, LPS) gets IJKToRAS diag(-0.5, -0.5, 0.5) plus its
    origin flipped; the volume sent with ``files`` lands on it, the one sent with ``plus`` turned 180 degrees
    about S from it, on PLUS's raw stream."""
    for placement in ("files", "plus"):
        from_file = _slicer_ijk_to_ras(runs[placement]["volume"])
        assert np.allclose(np.diag(from_file)[:3], [-0.5, -0.5, 0.5])
        sent = igtlio_ijk_to_ras(runs[placement]["client"].bodies("CorrectedVolume")[-1])[0]
        expected = sent if placement == "files" else LPS_TO_RAS @ sent
        assert np.allclose(from_file, expected, atol=1e-4), placement
