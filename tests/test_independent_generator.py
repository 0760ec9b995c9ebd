"""The independent generator's follow-up recordings and clinical-sweep geometry (benches/independent), without FEM."""

from __future__ import annotations

import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benches"))

from independent.cases import Protocol
from independent.clinical import Circle, Section, draw_specs, zero_force_pose
from independent.follow_up import record_follow_up
from independent.imaging import Scanner
from usdeform.io import read_sequence


def _case(kind: str, hidden: dict) -> dict:
    scanner = Scanner(64, 48, 40.0, 38.0, 6.0, 1.5, 0.5, 0.5, 5.0, -40.0, -20.0, 55.0, 10.0, 0.01, 0.2, 0)
    protocol = Protocol(0.3, 10.0, 4.0, 2.0, 0.02, 0.02, 20.0, 40)
    return {
        "kind": kind,
        "hidden_parameters": hidden,
        "scanner": asdict(scanner),
        "protocol": asdict(protocol),
        "texture_seed": 12345,
        "surface_to_base": np.eye(4).tolist(),
        "fem_cache": "unused",
    }


def _plan(tmp_path: Path, **entry: object) -> Path:
    path = tmp_path / "record_next.json"
    path.write_text(json.dumps({"format": "usdeform.record_next", "version": 1, "recordings": [entry]}))
    return path


def test_known_weight_records_the_load_and_the_sensor_reading(tmp_path: Path) -> None:
    hidden = {"bias_n": 0.5, "drift_n_per_s": 0.0, "gain_error": 0.08}
    plan = _plan(tmp_path, name="kw", kind="known_weight", known_weight_n=5.0, hold_s=3.0)
    (done,) = record_follow_up(_case("force_sensor_drift", hidden), plan, tmp_path / "out")
    recording = read_sequence(done["path"])
    header = Path(done["path"]).read_bytes().split(b"\n\n")[0].decode()
    loads = np.array([float(line.split(":=")[1]) for line in header.splitlines() if "_KnownLoad:=" in line])
    assert len(loads) == len(recording.timestamps) == done["frames"]
    loaded = loads > 4.999
    assert loaded.sum() > 40 and (loads < 1e-9).sum() > 20
    reading = np.asarray(recording.force)
    assert np.mean(reading[loaded]) == pytest.approx(1.08 * 5.0 + 0.5, abs=0.02)
    assert np.mean(reading[loads < 1e-9]) == pytest.approx(0.5, abs=0.02)


def test_record_next_errors_name_the_entry(tmp_path: Path) -> None:
    plan = _plan(tmp_path, name="kw", kind="known_weight", known_weight_n=None)
    with pytest.raises(ValueError, match="kw"):
        record_follow_up(_case("null", {}), plan, tmp_path / "out")
    plan = _plan(tmp_path, name="x", kind="wiggle")
    with pytest.raises(ValueError, match="wiggle"):
        record_follow_up(_case("null", {}), plan, tmp_path / "out")


def test_curved_path_turns_the_probe_axis_along_the_surface_normal() -> None:
    spec = next(s for s in draw_specs(3, quick=True) if s.shape == "curved")
    radius = spec.surface_radius_mm
    arc = np.linspace(0.0, spec.length_mm, 5)
    poses = zero_force_pose(spec, arc, np.eye(4))
    centre = np.array([0.0, 0.0, -radius])  # centre of curvature below the first contact point
    for pose, s in zip(poses, arc, strict=True):
        assert np.linalg.norm(pose[:3, 3] - centre) == pytest.approx(radius)
        inward = (centre - pose[:3, 3]) / radius
        assert pose[:3, 2] @ inward == pytest.approx(1.0)
        assert np.arccos(np.clip(pose[:3, 2] @ poses[0][:3, 2], -1, 1)) == pytest.approx(s / radius, abs=1e-9)
    assert 40.0 <= radius <= 100.0


def test_draw_covers_every_shape_and_force_range() -> None:
    specs = draw_specs(1, quick=True)
    assert {s.shape for s in specs} >= {"depth_radius", "branch", "artery_vein", "curved", "layered_bone"}
    assert any(s.force_n == 15.0 for s in specs) and any(2.0 <= s.force_n <= 10.0 for s in specs)
    depth = next(s for s in specs if s.shape == "depth_radius")
    depths = [depth.geometry(f).circles[0].depth_mm for f in (0.0, 1.0)]
    assert 10.0 <= min(depths) and max(depths) <= 30.0 and depths[1] - depths[0] > 8.0
    bone = next(s for s in specs if s.shape == "layered_bone").sections[0].bone
    assert 25.0 <= bone[1] <= 40.0
    vein = next(c for c in next(s for s in specs if s.shape == "artery_vein").sections[0].circles if c.vessel == "vein")
    assert 0.02 <= vein.ratio <= 0.04


def test_blended_section_interpolates_the_geometry() -> None:
    a = Section((Circle("v", 0.0, 10.0, 3.0, 0.1),))
    b = Section((Circle("v", 4.0, 20.0, 2.0, 0.1),))
    mid = a.blend(b, 0.25).circles[0]
    assert (mid.x_mm, mid.depth_mm, mid.radius_mm) == pytest.approx((1.0, 12.5, 2.75))
