"""Follow-up recordings of the independent generator: what a diagnosis's record_next.json asks for, recorded for the
same hidden effect and phantom as a case of ``cases.generate_case`` (see /work/notes/record_next.md for the contract).

Kinds (each entry one PLUS sequence file ``<name>.seq.nrrd``):

| kind | what is recorded |
|---|---|
| palpation, hold, ramp_speed | a load-hold-unload palpation with the entry's peak force, probe speed and hold |
| position | the same at ``position_mm`` along the surface (the phantom is uniform along it: new speckle only) |
| tilt | the probe rotated ``tilt_deg`` in the image plane, pressing along its own axis (a new FEM solve) |
| reference_target | a palpation imaged deep enough to show the table under the phantom (fixed in the world) |
| known_weight | the probe off the tissue, a calibrated weight put on and taken off; per-frame ``KnownLoad`` |

Every recording carries the case's hidden effect (timing, sensor, creep, sound speed, inclination, sliding...)
exactly as ``cases.record_palpation`` applies it to the first palpation.
"""

from __future__ import annotations

import json
import os
import zlib
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from usdeform.io import write_sequence
from usdeform.recording import Recording

from .cases import Protocol, Sweep, case_texture, record_palpation, sensed_force
from .imaging import _TEXTURE_DZ_MM, ASSUMED_SPEED_M_PER_S, Renderer, Scanner, Texture
from .mechanics import Face, Phantom, solve_phantom

TABLE_ECHO = 300.0
"""Amplitude of the table's specular echo against the tissue's unit scatterer amplitude (about +45 dB: a
specular tissue-table interface)."""


def _entry_protocol(entry: dict, base: Protocol, solution_forces: np.ndarray, lambda_at) -> tuple[Protocol, list[str]]:
    """The palpation protocol of one entry: its peak force (capped at 85 % of what the FEM reached), hold and
    probe speed (mm/s, turned into the force loop's ramp rate through the FEM's force curve); notes on caps."""
    notes = []
    reached = float(solution_forces[-1])
    peak = float(entry.get("max_force_n") or base.max_force_n)
    if peak > 0.85 * reached:
        notes.append(f"max_force_n {peak:.2f} N capped at {0.85 * reached:.2f} N (85 % of the FEM's reach)")
        peak = 0.85 * reached
    ramp = base.ramp_n_per_s
    speed = entry.get("ramp_speed_mm_s")
    if speed:
        travel = float(lambda_at(np.array(peak)) - lambda_at(np.array(base.contact_n)))
        ramp = float(speed) * (peak - base.contact_n) / max(travel, 1e-6)
    hold = entry.get("hold_s")
    hold = base.hold_s if hold is None else float(hold)
    duration = 2 * (peak - base.contact_n) / ramp + hold
    frames = min(int(duration * base.frame_rate_hz) + 1, 2 * base.max_frames)
    return replace(base, max_force_n=peak, ramp_n_per_s=ramp, hold_s=hold, max_frames=max(frames, 10)), notes


def _tilted(phantom: Phantom, tilt_deg: float) -> Phantom:
    """The phantom with the probe rotated ``tilt_deg`` more in the image plane: face and direction of travel turn
    together (the robot presses along its rotated axis)."""
    if not tilt_deg:
        return phantom
    if phantom.frictionless or phantom.lumen_pressure_kpa:
        raise ValueError("the independent generator records sliding contact and lumen pressure with a level probe only")
    return replace(phantom, face_tilt_deg=phantom.face_tilt_deg + tilt_deg, travel_deg=phantom.travel_deg - tilt_deg)


def _with_table(texture: Texture, phantom: Phantom, table_mm: float) -> Texture:
    """``texture`` (each elevation slice) extended below the phantom to the table: a specular line at ``table_mm``
    below the unloaded surface, fixed in the world with the phantom's base; gel between base and table if deeper;
    nothing below."""
    rows = int(np.ceil((table_mm + 4.0 - texture.z0) / _TEXTURE_DZ_MM)) + 1

    def extend(values: np.ndarray) -> np.ndarray:
        if rows > values.shape[0]:
            values = np.vstack([values, np.zeros((rows - values.shape[0], values.shape[1]), np.float32)])
        z = texture.z0 + np.arange(values.shape[0]) * _TEXTURE_DZ_MM
        values = np.where((z > phantom.depth_mm)[:, None], 0.0, values)
        return (values + (TABLE_ECHO * np.exp(-0.5 * ((z - table_mm) / 0.05) ** 2))[:, None]).astype(np.float32)

    texture.values = extend(texture.values)
    texture.slices = [(y, texture.values if y == 0.0 else extend(values)) for y, values in texture.slices]
    if texture.opacity is not None:
        extra = texture.values.shape[0] - texture.opacity.shape[0]
        texture.opacity = np.vstack([texture.opacity, np.zeros((extra, texture.opacity.shape[1]), np.float32)])
    return texture


def _deep_scanner(scanner: Scanner, reach_mm: float) -> Scanner:
    """The scanner with its imaging depth raised to ``reach_mm`` (5 mm steps), the pixel size kept."""
    depth = max(scanner.depth_mm, 5.0 * np.ceil(reach_mm / 5.0))
    return replace(scanner, depth_mm=float(depth), rows=round(scanner.rows * depth / scanner.depth_mm))


def _add_frame_field(path: Path, field: str, values: np.ndarray) -> None:
    """Adds the per-frame field ``Seq_FrameNNNN_<field>`` after each frame's ContactForce in a .seq.nrrd header,
    written beside the file and renamed over it."""
    data = path.read_bytes()
    end = data.index(b"\n\n") + 1
    lines = data[:end].decode().splitlines(keepends=True)
    out = []
    for line in lines:
        out.append(line)
        if line.startswith("Seq_Frame") and "_ContactForce:=" in line:
            index = int(line[len("Seq_Frame") : line.index("_", len("Seq_Frame"))])
            out.append(f"Seq_Frame{index:04d}_{field}:={values[index]:.6g}\n")
    temporary = path.with_name(path.name + ".part")
    temporary.write_bytes("".join(out).encode() + data[end:])
    os.replace(temporary, path)


def _known_weight(case: dict, entry: dict, rng: np.random.Generator, path: Path) -> dict:
    """The probe in its holder off the tissue: 1 s unloaded, the weight put on over 0.3 s, held ``hold_s`` (3 s if
    0), taken off over 0.3 s, 1 s unloaded; the sensor's reading (the case's sensor effect and noise) and the load
    truly applied (KnownLoad) per frame; blank frames, the probe 20 mm above the surface."""
    weight = entry.get("known_weight_n")
    if not weight:
        raise ValueError(f"record_next entry {entry.get('name')}: known_weight needs known_weight_n")
    protocol = Protocol(**case["protocol"])
    scanner = Scanner(**case["scanner"])
    hold = float(entry.get("hold_s") or 3.0)
    duration = 2.6 + hold
    t = np.arange(-1.0, duration + 0.5, 1e-3)
    on = np.clip(t - 1.0, 0, 0.3) / 0.3 - np.clip(t - 1.3 - hold, 0, 0.3) / 0.3
    load = float(weight) * on * on * (3 - 2 * on)
    times = np.arange(rng.uniform(0, 1 / protocol.frame_rate_hz), duration, 1 / protocol.frame_rate_hz)
    reading = sensed_force(case["kind"], case["hidden_parameters"], t, load, times, protocol.force_noise_n, rng)
    pose = np.diag([1.0, -1.0, -1.0, 1.0])
    pose[2, 3] = 20.0
    poses = np.asarray(case["surface_to_base"])[None] @ np.tile(pose, (len(times), 1, 1))
    recording = Recording(
        frames=np.zeros((len(times), scanner.rows, scanner.cols), np.uint8),
        timestamps=times,
        probe_to_base=poses,
        pose_valid=np.ones(len(times), dtype=bool),
        image_to_probe=scanner.image_to_probe(),
        force=reading,
        probe_displacement=np.zeros(len(times)),
    )
    write_sequence(path, recording)
    _add_frame_field(path, "KnownLoad", np.interp(times, t, load))
    return {"frames": len(times), "seconds": float(times[-1] - times[0]), "known_weight_n": float(weight)}


def _palpation(case: dict, entry: dict, rng: np.random.Generator, path: Path) -> dict:
    """A palpation of the entry's kind (see the module's table) for the case's phantom and hidden effect."""
    kind, hidden = case["kind"], case["hidden_parameters"]
    phantom = _tilted(Phantom(**case["phantom"]), float(entry.get("tilt_deg") or 0.0))
    scanner = Scanner(**case["scanner"])
    solution = solve_phantom(phantom, Path(case["fem_cache"]))
    protocol, notes = _entry_protocol(entry, Protocol(**case["protocol"]), solution.forces, solution.lambda_at)
    first = float(case.get("position_mm", 0.0))
    position = float(entry.get("position_mm") if entry.get("position_mm") is not None else first)
    seed = int(case["texture_seed"])
    if abs(position - first) > 1e-6:  # elsewhere on the uniform phantom: other scatterers, the same kind of tissue
        seed = int(np.random.default_rng([seed, zlib.crc32(f"{position:.3f}".encode())]).integers(2**63))
    metadata: dict[str, str] = {}
    table = None
    if entry["kind"] == "reference_target":
        asked = entry.get("reference_depth_mm")
        table = phantom.depth_mm if asked is None else float(asked)
        if table < phantom.depth_mm - 1e-6:
            raise ValueError(
                f"record_next entry {entry.get('name')}: the independent generator has a reflector fixed in the world "
                f"only at or below the phantom's base ({phantom.depth_mm:.1f} mm); asked {table:.1f} mm"
            )
        scanner = _deep_scanner(scanner, table * 1.12 + 4.0)  # displayed deeper than true under a slow tissue
        metadata["ReferenceTargetDepth"] = f"{table:.3f}"
    texture = case_texture(kind, hidden, phantom, scanner, seed)
    if table is not None:
        texture = _with_table(texture, phantom, table)
    speed = hidden.get("sound_speed_m_per_s", ASSUMED_SPEED_M_PER_S)
    face = Face.of(phantom, solution.lift_mm)
    renderer = Renderer(solution, texture, scanner, face, speed / ASSUMED_SPEED_M_PER_S)
    recording, timeline = record_palpation(
        kind,
        hidden,
        solution,
        protocol,
        renderer,
        face,
        scanner,
        rng,
        surface_to_base=np.asarray(case["surface_to_base"]),
        sweep=Sweep(0.0, 0.0, position, position),  # the beam in the texture's own slices
    )
    if metadata:
        recording = Recording(**{**{k: getattr(recording, k) for k in _FIELDS}, "metadata": metadata})
    write_sequence(path, recording)
    times = np.asarray(recording.timestamps)
    return {
        "frames": len(times),
        "seconds": float(times[-1] - times[0]),
        "protocol": asdict(protocol),
        "position_mm": position,
        "face_tilt_deg": phantom.face_tilt_deg,
        "table_depth_mm": table,
        "peak_lambda_mm": float(timeline["frame_lambda"].max()),
        "notes": notes,
    }


_FIELDS = ("frames", "timestamps", "probe_to_base", "pose_valid", "image_to_probe", "force", "probe_displacement")
KINDS = ("palpation", "hold", "ramp_speed", "position", "tilt", "reference_target", "known_weight")


def record_follow_up(case: dict, record_next_path: str | Path, output_dir: str | Path) -> list[dict]:
    """Records every recording ``record_next_path`` (a record_next.json) asks for, for the case's hidden effect and
    phantom, into ``output_dir / <name>.seq.nrrd``.

    ``case``: the dict ``cases.generate_case`` returns (a row of benches/gap_independent.py's cases.jsonl holds it):
    ``kind``, ``hidden_parameters``, ``phantom``, ``scanner``, ``protocol``, ``texture_seed``, ``surface_to_base``,
    ``fem_cache`` (and ``position_mm``, the first palpation's place along the surface, 0 if absent). Each entry's
    recording is seeded from the texture seed and the entry's name, so a case records the same follow-up every time.
    Returns one dict per entry, in the file's order: ``name``, ``kind``, ``path``, ``frames``, ``seconds`` (of
    recording), and what was recorded (protocol, position, tilt, table depth, notes on capped forces).
    Raises ValueError naming the entry for a kind or parameter the generator cannot record."""
    plan = json.loads(Path(record_next_path).read_text())
    if plan.get("format") != "usdeform.record_next":
        raise ValueError(f"{record_next_path}: format is {plan.get('format')!r}, expected 'usdeform.record_next'")
    output = Path(output_dir)
    output.mkdir(parents=True, exist_ok=True)
    done = []
    for index, entry in enumerate(plan.get("recordings", [])):
        if entry.get("kind") not in KINDS:
            raise ValueError(f"{record_next_path}: recording {index} has kind {entry.get('kind')!r}; known: {KINDS}")
        name = str(entry.get("name") or f"follow_up_{index + 1:02d}_{entry['kind']}")
        rng = np.random.default_rng([int(case["texture_seed"]), zlib.crc32(name.encode()), 7])
        path = output / f"{name}.seq.nrrd"
        if entry["kind"] == "known_weight":
            info = _known_weight(case, entry, rng, path)
        else:
            info = _palpation(case, entry, rng, path)
        done.append({"name": name, "kind": entry["kind"], "path": str(path), "reveals": entry.get("reveals"), **info})
    return done
