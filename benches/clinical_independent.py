"""usdeform's 3D correction on sweeps shaped like clinical scans, made by the independent generator
(benches/independent/clinical.py); usdeform used only through its command line, with default settings.

Per sweep: ``usdeform fit palpation_1 palpation_2 --output model.json --flexible-layer-mm D`` (D: the depth of the
bone's top where there is one, else the tissue's depth, as a user who saw or measured it would give it) and
``usdeform correct sweep.seq.nrrd --model model.json --output corrected.seq.nrrd``; ``--clamp-force`` is added (and
recorded) only when ``correct`` refuses forces outside the fitted range. A failure is recorded with its command and
message.

Scoring, per vessel, on the uncorrected (deformed) and the corrected sweep, against the zero-force lumen of that
vessel in each frame's own plane (truth.npz):
- segmentation: ``compensation_independent.segment`` (the anechoic threshold, the component nearest an expected
  centre) at each of the vessel's lumen centres at zero force; a component is kept for the vessel when its centroid
  lies within 8 mm of that centre and no nearer another vessel's centre (two discs of a branching vessel: the union);
- Dice per frame (mean and worst frame), lumen area error per frame (%; the vein's worst frame reported);
- volume error (%): the areas summed along the path with the arc length between frames as weights (over a curved
  surface scaled by (R - depth) / R at the true lumen's centroid: Pappus), against the truth's;
- centre line error (mm): the mean 3D distance between the segmented lumen's centroid placed by the file's pose and
  calibration and the true centroid placed by the zero-force pose;
- calibration of the segmentation: the B-mode point spread and the bright wall make a lumen look smaller than it
  is (by about 0.3 mm of radius), the same in every frame; each segmented mask is grown by the margin (0-1.2 mm)
  that maximises the mean Dice on both palpations' first frames (0.3 N, about zero force) against the truth there.
  The Dice reached there is the segmentation's check at two places;
- the segmentation's ceiling per vessel: the same measures on the sweep's frames rendered at zero indentation by
  the generator's renderer at the zero-force poses (zero_force.seq.nrrd): what a perfect correction would score;
- pixels without data: a corrected file's validity mask (its companion .valid file) marks the pixels the
  correction sampled from outside the frame; they are refilled from the nearest pixel with data before segmenting
  and left out of the masks after.
A correction is "worse than none" on a measure when its value is worse than the deformed sweep's.

    python benches/clinical_independent.py --seed 1 --out clinical-independent
    python benches/clinical_independent.py --seed 1 --quick --sweeps 8 --out DIR

Sweeps already generated in DIR are kept unless ``--fresh``; FEM solves are cached in DIR/fem_cache.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import distance_transform_edt, label

from compensation_independent import _run, segment
from independent.clinical import describe, draw_specs, generate
from usdeform.io import read_sequence, write_sequence
from usdeform.recording import Recording

TARGETS = {"dice_mean": 0.98, "dice_worst": 0.95, "volume_pct": 2.0, "centre_line_mm": 0.2, "vein_area_pct": 5.0}


def _refilled(frame: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """``frame`` with its pixels without data (``valid`` False: the corrected file's mask) set to the nearest
    pixel with data, so that no black band reads as lumen."""
    if valid is None or valid.all() or not valid.any():
        return frame
    nearest = distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return frame[tuple(nearest)]


def _segment_vessels(
    frame: np.ndarray,
    spacing: tuple[float, float],
    centres: dict[str, list[tuple[float, float]]],
    valid: np.ndarray | None = None,
):
    """Mask per vessel (see the module's docstring); ``centres``: (row, col) pixels of each vessel's lumen discs;
    ``valid``: the pixels with data (None: all), the others refilled before and left out after segmenting."""
    dz, dx = spacing
    frame = _refilled(frame, valid)
    everyone = [(v, c) for v, cs in centres.items() for c in cs]
    masks = {}
    for vessel, points in centres.items():
        mask = np.zeros(frame.shape, dtype=bool)
        for centre in points:
            found = segment(frame, spacing, centre)
            if not found.any():
                continue
            rows, cols = np.nonzero(found)
            here = np.array([rows.mean(), cols.mean()])

            def distance(c: tuple[float, float], here: np.ndarray = here) -> float:
                return float(np.hypot((here[0] - c[0]) * dz, (here[1] - c[1]) * dx))

            own = distance(centre)
            others = [distance(c) for v, c in everyone if v != vessel]
            if own < 8.0 and all(own <= d for d in others):
                mask |= found
        masks[vessel] = mask if valid is None else mask & valid
    return masks


def _centroid_world(pose: np.ndarray, image_to_probe: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    if not mask.any():
        return None
    rows, cols = np.nonzero(mask)
    return (pose @ image_to_probe @ np.array([cols.mean(), rows.mean(), 0.0, 1.0]))[:3]


def _dilate(mask: np.ndarray, spacing: tuple[float, float], mm: float) -> np.ndarray:
    if mm <= 0 or not mask.any():
        return mask
    return distance_transform_edt(~mask, sampling=spacing) <= mm


def score(path: Path, truth: dict, spec_info: dict, dilate_mm: float = 0.0, frames_of: slice = slice(None)) -> dict:
    """Per-vessel measures of one sequence file against the zero-force truth (see the module's docstring); each
    segmented mask grown by ``dilate_mm`` (the segmentation's calibration)."""
    recording = read_sequence(path)
    frames = np.asarray(recording.frames)[frames_of]
    valid = None if recording.pixel_valid is None else np.asarray(recording.pixel_valid)[frames_of]
    calibration = np.asarray(recording.image_to_probe)
    poses = np.asarray(recording.probe_to_base)
    dx, dz = float(np.linalg.norm(calibration[:3, 0])), float(np.linalg.norm(calibration[:3, 1]))
    vessels = [k[len("zero_force_") :] for k in truth if k.startswith("zero_force_") and k != "zero_force_pose"]
    arc = truth["arc_mm"]
    step = np.gradient(arc) if len(arc) > 1 else np.ones(1)
    radius = spec_info["surface_radius_mm"]
    seg = {v: [] for v in vessels}
    for k, frame in enumerate(frames):
        centres = {}
        for v in vessels:  # the zero-force discs' centres: the truth mask's components
            labels, count = label(truth[f"zero_force_{v}"][k])
            centres[v] = [tuple(np.argwhere(labels == i).mean(axis=0)) for i in range(1, count + 1)]
        masks = _segment_vessels(frame, (dz, dx), centres, None if valid is None else valid[k])
        for v, mask in masks.items():
            seg[v].append(_dilate(mask, (dz, dx), dilate_mm))
    result = {}
    for v in vessels:
        true_masks, masks = truth[f"zero_force_{v}"], np.stack(seg[v])
        inter = (true_masks & masks).sum(axis=(1, 2))
        dice = 2 * inter / np.maximum(true_masks.sum(axis=(1, 2)) + masks.sum(axis=(1, 2)), 1)
        true_area = true_masks.sum(axis=(1, 2)) * dx * dz
        area = masks.sum(axis=(1, 2)) * dx * dz
        depth = np.array([np.nonzero(m)[0].mean() * dz for m in true_masks])
        weight = step * ((radius - depth) / radius if radius else 1.0)
        distances = []
        for k in range(len(frames)):
            true_point = _centroid_world(truth["zero_force_pose"][k], calibration, true_masks[k])
            point = _centroid_world(poses[k], calibration, masks[k])
            distances.append(
                np.nan if point is None or true_point is None else float(np.linalg.norm(point - true_point))
            )
        distances_array = np.array(distances)
        area_error = 100 * (area - true_area) / true_area
        result[v] = {
            "dice_mean": float(dice.mean()),
            "dice_worst": float(dice.min()),
            "volume_pct": float(100 * ((area * weight).sum() / (true_area * weight).sum() - 1)),
            "centre_line_mm": float(np.nanmean(distances_array)) if np.isfinite(distances_array).any() else None,
            "frames_missed": int((~masks.any(axis=(1, 2))).sum()),
            "area_pct_mean": float(area_error.mean()),
            "area_pct_worst": float(area_error[np.argmax(np.abs(area_error))]),
        }
    return result


def calibrate(directory: Path, spec) -> dict:
    """The segmentation's growth (mm, 0-1.2 in 0.05 steps) that maximises the mean Dice over the vessels on the
    first frames (0.3 N, about zero force) of both palpations against the zero-force truth at their places; the Dice
    there with and without it (the segmentation's check)."""
    from independent.clinical import truth_masks

    frames = {}
    for index, place in ((1, 0.1), (2, 0.9)):
        path = directory / f"palpation_{index}.seq.nrrd"
        masks = truth_masks(spec, np.array([place]))
        pose = np.asarray(read_sequence(path).probe_to_base)[:1]
        frames[path] = {
            **{f"zero_force_{k}": v for k, v in masks.items()},
            "zero_force_pose": pose,
            "arc_mm": np.zeros(1),
        }

    def dice(grow: float) -> float:
        values = [
            m["dice_mean"]
            for path, truth in frames.items()
            for m in score(path, truth, {"surface_radius_mm": 0.0}, grow, slice(0, 1)).values()
        ]
        return float(np.mean(values))

    grid = np.arange(0.0, 1.21, 0.05)
    values = [dice(g) for g in grid]
    best = int(np.argmax(values))
    return {"grow_mm": float(grid[best]), "contact_dice": values[best], "contact_dice_ungrown": values[0]}


def zero_force_sequence(spec, directory: Path, cache: Path) -> Path:
    """The sweep's frames rendered at zero indentation by the generator's own renderer (same tissue, texture and
    speckle, a fresh noise draw) at the zero-force poses, written once to zero_force.seq.nrrd: scored like the
    sweep, it is the Dice a perfect correction would reach under this segmentation (the segmentation's ceiling)."""
    from independent.clinical import Speckle, record, solve_section, structure

    path = directory / "zero_force.seq.nrrd"
    if path.exists():
        return path
    truth = np.load(directory / "truth.npz")
    sweep = read_sequence(directory / "sweep.seq.nrrd")
    rng = np.random.default_rng(spec.seed)  # as the generator draws its tissue structure and speckle
    shared = structure(spec, rng)
    speckle = Speckle(shared["shape"], int(rng.integers(2**63)))
    solutions = [solve_section(spec, i, cache) for i in range(len(spec.sections))]
    fractions = truth["fractions"]
    frames = record(spec, solutions, shared, speckle, fractions, np.zeros(len(fractions)), rng)
    write_sequence(
        path,
        Recording(
            frames=np.stack(frames),
            timestamps=sweep.timestamps,
            probe_to_base=truth["zero_force_pose"],
            pose_valid=np.ones(len(frames), dtype=bool),
            image_to_probe=sweep.image_to_probe,
        ),
    )
    return path


def run_sweep(spec, out: Path, fresh: bool) -> dict:
    directory = out / spec.name
    row: dict = {"sweep": spec.name, "shape": spec.shape, "spec": describe(spec)}
    start = time.perf_counter()
    info_path = directory / "info.json"
    if fresh or not info_path.exists():
        info = generate(spec, directory, out / "fem_cache")
        info_path.write_text(json.dumps(info))
        (directory / "zero_force.seq.nrrd").unlink(missing_ok=True)
    row["generation"] = json.loads(info_path.read_text())
    row["generation_s"] = time.perf_counter() - start
    bone = spec.sections[0].bone
    layer_mm = bone[1] if bone[2] > 0 else spec.phantom.depth_mm
    row["flexible_layer_mm"] = layer_mm
    log = directory / "usdeform.log"
    log.write_text("")
    palpations = [str(directory / f"palpation_{i}.seq.nrrd") for i in (1, 2)]
    model = directory / "model.json"
    fit = ["usdeform", "fit", *palpations, "--output", str(model), "--flexible-layer-mm", f"{layer_mm:.2f}"]
    ok, message, row["fit_s"] = _run(fit, log)
    if not ok:
        row["failure"] = {"command": " ".join(fit), "message": message}
        return row
    corrected = directory / "corrected.seq.nrrd"
    command = [
        "usdeform",
        "correct",
        str(directory / "sweep.seq.nrrd"),
        "--model",
        str(model),
        "--output",
        str(corrected),
    ]
    ok, message, row["correct_s"] = _run(command, log)
    row["clamped"] = False
    if not ok and ("clamp" in message.lower() or "range" in message.lower()):
        row["refused"] = message
        command.append("--clamp-force")
        ok, message, more = _run(command, log)
        row["correct_s"] += more
        row["clamped"] = True
    if not ok:
        row["failure"] = {"command": " ".join(command), "message": message}
        return row
    truth = dict(np.load(directory / "truth.npz"))
    spec_info = {"surface_radius_mm": spec.surface_radius_mm}
    row["segmentation"] = calibrate(directory, spec)
    grow = row["segmentation"]["grow_mm"]
    row["deformed"] = score(directory / "sweep.seq.nrrd", truth, spec_info, grow)
    row["corrected"] = score(corrected, truth, spec_info, grow)
    row["zero_force"] = score(zero_force_sequence(spec, directory, out / "fem_cache"), truth, spec_info, grow)
    return row


def _worse(deformed: dict, corrected: dict, vessel: str) -> list[str]:
    """Measures on which the correction is worse than none."""
    worse = []
    if corrected["dice_mean"] < deformed["dice_mean"]:
        worse.append("Dice mean")
    if corrected["dice_worst"] < deformed["dice_worst"]:
        worse.append("Dice worst")
    if abs(corrected["volume_pct"]) > abs(deformed["volume_pct"]):
        worse.append("volume")
    if (corrected["centre_line_mm"] or np.inf) > (deformed["centre_line_mm"] or np.inf):
        worse.append("centre line")
    if vessel == "vein" and abs(corrected["area_pct_worst"]) > abs(deformed["area_pct_worst"]):
        worse.append("vein area")
    return worse


def _meets(c: dict, vessel: str) -> bool:
    ok = c["dice_mean"] >= TARGETS["dice_mean"] and c["dice_worst"] >= TARGETS["dice_worst"]
    ok = ok and abs(c["volume_pct"]) <= TARGETS["volume_pct"]
    ok = ok and c["centre_line_mm"] is not None and c["centre_line_mm"] <= TARGETS["centre_line_mm"]
    return ok and (vessel != "vein" or abs(c["area_pct_worst"]) <= TARGETS["vein_area_pct"])


def _f(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _ceiling(z: dict | None) -> str:
    return "-" if z is None else f"{_f(z['dice_mean'])} / {_f(z['dice_worst'])}, {_f(z['volume_pct'], 1)}"


def table(rows: list[dict], command: str) -> str:
    """The markdown summary: one row per vessel of each sweep, then the worst per shape."""
    lines = [
        "# usdeform correct on clinical sweeps of the independent generator",
        "",
        f"Command: `{command}`",
        "",
        "Targets: Dice mean >= 0.98, worst frame >= 0.95, volume within 2 %, centre line within 0.2 mm, vein area "
        "within 5 % at every frame (the vein is open at zero force in every frame).",
        "",
        "| sweep | force N | vessel | Dice deformed mean / worst | Dice corrected mean / worst | volume % deformed / "
        "corrected | centre line mm deformed / corrected | area % worst frame deformed / corrected | seg. Dice at "
        "contact (growth mm) | zero-force frames: Dice mean / worst, volume % | "
        "meets targets | worse than none on |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    per_shape: dict[str, list[tuple[str, dict, bool, list[str]]]] = {}
    for row in rows:
        force = row["generation"]["sweep_force_n"]
        if "failure" in row:
            lines.append(
                f"| {row['sweep']} | {force:.1f} | all | failed: `{row['failure']['command']}`: "
                f"{row['failure']['message']} | | | | | | | |"
            )
            per_shape.setdefault(row["shape"], []).append(("failed", {}, False, []))
            continue
        for vessel in sorted(row["corrected"]):
            d, c = row["deformed"][vessel], row["corrected"][vessel]
            worse = _worse(d, c, vessel)
            meets = _meets(c, vessel)
            per_shape.setdefault(row["shape"], []).append((vessel, c, meets, worse))
            lines.append(
                f"| {row['sweep']}{' (clamped)' if row.get('clamped') else ''} | {force:.1f} | {vessel} | "
                f"{_f(d['dice_mean'])} / {_f(d['dice_worst'])} | {_f(c['dice_mean'])} / {_f(c['dice_worst'])} | "
                f"{_f(d['volume_pct'], 1)} / {_f(c['volume_pct'], 1)} | {_f(d['centre_line_mm'], 2)} / "
                f"{_f(c['centre_line_mm'], 2)} | {_f(d['area_pct_worst'], 1)} / {_f(c['area_pct_worst'], 1)} | "
                f"{_f(row['segmentation']['contact_dice'])} ({row['segmentation']['grow_mm']:.2f}) | "
                f"{_ceiling(row.get('zero_force', {}).get(vessel))} | {'yes' if meets else 'no'} | "
                f"{', '.join(worse) or '-'} |"
            )
    lines += [
        "",
        "| shape | vessels scored | meet all targets | worst corrected Dice (worst frame) | worse than none |",
    ]
    lines.append("|---|---|---|---|---|")
    for shape, entries in per_shape.items():
        scored = [e for e in entries if e[1]]
        worst = min((e[1]["dice_worst"] for e in scored), default=None)
        worse = sorted({w for e in scored for w in e[3]})
        lines.append(
            f"| {shape} | {len(scored)} of {len(entries)} | {sum(e[2] for e in scored)} | {_f(worst)} | "
            f"{', '.join(worse) or '-'} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sweeps", type=int, default=8, help="how many of the run's sweeps (8: every shape)")
    parser.add_argument("--out", type=Path, default=Path("clinical-independent"))
    parser.add_argument("--quick", action="store_true", help="coarse mesh, 192 x 150 pixels, 30 sweep frames")
    parser.add_argument("--fresh", action="store_true", help="generate sweeps already in DIR again")
    parser.add_argument("--only", default=None, help="comma-separated sweep names of the run (e.g. 02_artery_vein)")
    args = parser.parse_args(argv)
    command = "python benches/clinical_independent.py " + " ".join(sys.argv[1:] if argv is None else argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    chosen = draw_specs(args.seed, args.quick)[: args.sweeps]
    if args.only:
        chosen = [spec for spec in chosen if spec.name in args.only.split(",")]
    for spec in chosen:
        start = time.perf_counter()
        try:
            row = run_sweep(spec, args.out, args.fresh)
        except Exception as exc:  # a failure of the generator or the scoring is recorded, the others go on
            row = {"sweep": spec.name, "shape": spec.shape, "error": f"{type(exc).__name__}: {exc}"}
        row["seconds"] = time.perf_counter() - start
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "spec"}), flush=True)
        with (args.out / "results.jsonl").open("a") as handle:
            handle.write(json.dumps(row) + "\n")
    text = table([r for r in rows if "error" not in r], command)
    text += "".join(f"\nGenerator or scoring error on {r['sweep']}: {r['error']}\n" for r in rows if "error" in r)
    (args.out / "clinical.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
