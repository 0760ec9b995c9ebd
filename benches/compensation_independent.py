"""What a withheld recording effect costs usdeform's corrected sweep, and what ``--compensate`` gives back, on
recordings from the independent generator (benches/independent; usdeform used only through its command line).

Each case (``independent.sweep``) is one drawn phantom, scanner and hidden effect recorded as two palpations and a
force-controlled sweep along elevation, twice from the same seeds: with the effect and without it. Per case:

- (a) effect, no compensation: ``usdeform fit P1 P2 --flexible-layer-mm D`` (D the phantom's tissue depth under the
  probe, as a user who measured it would give it) and ``usdeform correct sweep --output corrected.seq.nrrd``;
  ``--clamp-force`` is added (and recorded) only when ``correct`` refuses forces outside the fitted range;
- (b) the same with ``--compensate diagnosis.json`` on fit and correct, the diagnosis from ``usdeform diagnose P1 P2``
  run blind on the palpations with the effect; a refusal (non-zero exit) makes (b) = (a), recorded;
- (e) as (b) with ``--force-compensation`` too;
- (d) the case without the effect, no compensation (for a null case the files are (a)'s, so (d) = (a)).

Scoring (own segmentation, ``segment``): each corrected frame smoothed (Gaussian, 0.5 mm), thresholded at 80 % of
the way from the lumen's grey (the 1st percentile of the smoothed frame) to the tissue's (its median): the lumen
abuts a brighter wall, so half-way undersegments it by 10-15 % of its area on the generator's frames, 80 % by
about 4 % (the lumen is anechoic: its echo 34 dB below the tissue's, above only the noise floor; black pixels a
correction left empty are left out), holes filled, opened (1 mm element), the connected component of at least
3 mm^2 whose centroid is nearest the expected centre (the zero-force lumen's) kept. Against the zero-force truth
(the undeformed lumen at first contact, true mm; ``independent.sweep.zero_force_mask`` on the corrected file's own
calibration): Dice, lumen area error (%), lumen centroid depth error (mm); the uncorrected sweep is scored the same
way for reference, and the segmentation is checked on the uncorrected frames of the case without the effect
against the deformed lumen actually imaged.

Per kind (benchmark.md): cases, costly cases (mean Dice (d) - (a) >= 0.01 or mean |area error| (a) - (d) >= 2 %),
median cost, median recovered share ((b) - (a)) / ((d) - (a)) over the costly cases (Dice; and for (e)), cases
made worse by compensation (Dice (b) < (a) - 0.005), and for nulls whether (b) equals (a) exactly (the same
corrected frames).

    python benches/compensation_independent.py --cases 5 --seed 1 --quick --out comp-independent
    python benches/compensation_independent.py --cases 10 --kinds image_latency,null --out DIR --workers 2

Seeds: ``SeedSequence(seed)`` spawns one stream per case (child i for case i, whatever ``--cases``); the case's
draw and its recordings take children of it. FEM solves are cached in DIR/fem_cache; cases already in
DIR/cases.jsonl with the same seed, mode and kind are kept unless ``--fresh``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import binary_fill_holes, gaussian_filter, label

from independent.cases import kinds_to_cycle
from independent.sweep import KINDS, children, draw, generate_sweep_case, zero_force_mask
from usdeform.io import read_sequence

DEFAULT_KINDS = ("image_latency", "force_sensor_error", "viscoelasticity", "sound_speed_mismatch", "null")
RUNS = ("a", "b", "e", "d")


def _run(command: list[str], log: Path) -> tuple[bool, str, float]:
    """Runs a usdeform command; (ok, last stderr line or '', seconds); its output appended to ``log``."""
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    with log.open("a") as handle:
        handle.write(f"$ {' '.join(command)}\n(exit {result.returncode}, {seconds:.1f} s)\n")
        handle.write(result.stdout + result.stderr + "\n")
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    return result.returncode == 0, (lines[-1] if lines else ""), seconds


def segment(frame: np.ndarray, spacing: tuple[float, float], centre: tuple[float, float]) -> np.ndarray:
    """Lumen mask of one frame: smoothed, anechoic threshold, holes filled, opened, the component nearest
    ``centre`` (row, col in pixels) of at least 3 mm^2 (an empty mask if none)."""
    dz, dx = spacing
    smooth = gaussian_filter(frame.astype(np.float32), (0.5 / dz, 0.5 / dx))
    filled = smooth[smooth > 8.0]  # leave out pixels a correction left empty (black)
    if filled.size < 100:
        return np.zeros(frame.shape, dtype=bool)
    lumen, tissue = float(np.percentile(filled, 1)), float(np.median(filled))
    dark = (smooth < lumen + 0.8 * (tissue - lumen)) & (smooth > 8.0)
    dark = binary_fill_holes(dark)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (max(3, round(1.0 / dx) | 1), max(3, round(1.0 / dz) | 1)))
    dark = cv2.morphologyEx(dark.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    labels, count = label(dark)
    best, distance = 0, np.inf
    for index in range(1, count + 1):
        rows, cols = np.nonzero(labels == index)
        if len(rows) * dz * dx < 3.0:
            continue
        d = np.hypot((rows.mean() - centre[0]) * dz, (cols.mean() - centre[1]) * dx)
        if d < distance:
            best, distance = index, d
    return labels == best if best else np.zeros_like(dark)


def _metrics(mask: np.ndarray, truth: np.ndarray, dz: float) -> dict[str, float]:
    inter = float(np.logical_and(mask, truth).sum())
    total = float(mask.sum() + truth.sum())
    dice = 2 * inter / total if total else 1.0
    area = 100.0 * (float(mask.sum()) - float(truth.sum())) / max(float(truth.sum()), 1.0)
    if mask.any():
        depth = (np.nonzero(mask)[0].mean() - np.nonzero(truth)[0].mean()) * dz
    else:
        depth = float("nan")
    return {"dice": dice, "area_error_pct": area, "depth_error_mm": float(depth)}


def score_sequence(path: Path, phantom: dict, face_args: dict, truth: np.ndarray | None = None) -> dict:
    """Per-frame Dice, area error and centroid depth error of the segmented lumen against the zero-force truth on
    the file's own calibration (or against ``truth`` per frame, (n, rows, cols)); means and worst."""
    from independent.mechanics import Face, Phantom

    recording = read_sequence(path)
    frames = np.asarray(recording.frames)
    calibration = np.asarray(recording.image_to_probe)
    dx, dz = float(np.linalg.norm(calibration[:3, 0])), float(np.linalg.norm(calibration[:3, 1]))
    model = Phantom(**phantom)
    zero = zero_force_mask(model, Face.of(model, **face_args), frames.shape[1:], calibration)
    rows, cols = np.nonzero(zero)
    centre = (rows.mean(), cols.mean())
    per_frame = []
    for k, frame in enumerate(frames):
        mask = segment(frame, (dz, dx), centre)
        per_frame.append(_metrics(mask, zero if truth is None else truth[k], dz))
    dice = np.array([m["dice"] for m in per_frame])
    area = np.array([m["area_error_pct"] for m in per_frame])
    depth = np.array([m["depth_error_mm"] for m in per_frame])
    return {
        "frames": len(frames),
        "dice_mean": float(dice.mean()),
        "dice_min": float(dice.min()),
        "area_error_pct_mean": float(area.mean()),
        "abs_area_error_pct_mean": float(np.abs(area).mean()),
        "depth_error_mm_mean": float(np.nanmean(depth)) if np.isfinite(depth).any() else None,
        "pixel_mm": [dz, dx],
        "frames_md5": _digest(frames),
    }


def _digest(frames: np.ndarray) -> str:
    import hashlib

    return hashlib.md5(np.ascontiguousarray(frames).tobytes()).hexdigest()


def _fit_correct(
    name: str, palpations: list[Path], sweep: Path, depth_mm: float, directory: Path, extra: list[str]
) -> dict:
    """fit + correct into ``directory / name``; the outcome (ok, error's last line, clamp, seconds)."""
    out = directory / name
    out.mkdir(parents=True, exist_ok=True)
    log = out / "usdeform.log"
    log.write_text("")
    model = out / "model.json"
    row: dict[str, object] = {"extra": extra}
    ok, message, seconds = _run(
        [
            "usdeform",
            "fit",
            *map(str, palpations),
            "--output",
            str(model),
            "--flexible-layer-mm",
            f"{depth_mm:.2f}",
            *extra,
        ],
        log,
    )
    row["fit_s"] = seconds
    if not ok:
        return {**row, "ok": False, "stage": "fit", "error": message}
    corrected = out / "corrected.seq.nrrd"
    command = ["usdeform", "correct", str(sweep), "--model", str(model), "--output", str(corrected), *extra]
    ok, message, seconds = _run(command, log)
    row["clamped"] = False
    if not ok and ("clamp" in message.lower() or "range" in message.lower()):
        row["refused_forces"] = message
        ok, message, more = _run([*command, "--clamp-force"], log)
        seconds += more
        row["clamped"] = True
    row["correct_s"] = seconds
    if not ok:
        return {**row, "ok": False, "stage": "correct", "error": message}
    return {**row, "ok": True, "corrected": str(corrected)}


def run_case(index: int, kind: str, seed: int, quick: bool, out: Path) -> dict:
    """``_case``, a failure of the generator or the scoring recorded in the row instead of ending the run."""
    try:
        return _case(index, kind, seed, quick, out)
    except Exception as exc:  # recorded, the other cases go on
        return {"case": index, "seed": seed, "quick": quick, "kind": kind, "error": f"{type(exc).__name__}: {exc}"}


def _case(index: int, kind: str, seed: int, quick: bool, out: Path) -> dict:
    """Generates, diagnoses, fits, corrects and scores case ``index``; returns its row."""
    draw_seed, record_seed = children(children(np.random.SeedSequence(seed), index + 1)[index], 2)
    directory = out / f"case_{index:03d}"
    row: dict[str, object] = {"case": index, "seed": seed, "quick": quick, "kind": kind}
    row["usdeform"] = _usdeform_version()
    timings: dict[str, float] = {}
    start = time.perf_counter()
    drawn = draw(kind, draw_seed, quick)
    effect_info = generate_sweep_case(drawn, record_seed, directory / "effect", out / "fem_cache", True, quick)
    if kind == "null":
        clean_info = effect_info
        clean_dir = directory / "effect"
    else:
        clean_dir = directory / "clean"
        clean_info = generate_sweep_case(drawn, record_seed, clean_dir, out / "fem_cache", False, quick)
    timings["generation_s"] = time.perf_counter() - start
    effect_sweep = read_sequence(directory / "effect" / "sweep.seq.nrrd")
    clean_sweep = read_sequence(clean_dir / "sweep.seq.nrrd")
    row["effect_vs_clean"] = {  # what the effect changed in the sweep (the rest must be the same case)
        name: bool(np.array_equal(np.asarray(getattr(effect_sweep, name)), np.asarray(getattr(clean_sweep, name))))
        for name in ("frames", "timestamps", "probe_to_base", "force", "probe_displacement")
    }
    row.update({k: v for k, v in effect_info.items() if k not in ("kind",)})
    depth = float(drawn.phantom.depth_mm)
    row["flexible_layer_mm"] = depth
    effect_palpations = [directory / "effect" / f"palpation_{i}.seq.nrrd" for i in (1, 2)]
    clean_palpations = [clean_dir / f"palpation_{i}.seq.nrrd" for i in (1, 2)]
    diagnosis_dir = directory / "diagnosis"
    diagnosis_dir.mkdir(parents=True, exist_ok=True)
    ok, message, timings["diagnosis_s"] = _run(
        ["usdeform", "diagnose", *map(str, effect_palpations), "--out", str(diagnosis_dir)],
        diagnosis_dir / "usdeform.log",
    )
    diagnosis = diagnosis_dir / "diagnosis.json"
    if ok and diagnosis.exists():
        result = json.loads(diagnosis.read_text())
        top = (result.get("effects") or [{}])[0]
        row["diagnosis"] = {
            "verdict": result.get("verdict"),
            "named": result.get("named"),
            "top": top.get("effect"),
            "top_parameters": top.get("parameters"),
            "top_shrink": top.get("shrink"),
            "compensation": result.get("compensation"),
        }
    else:
        row["diagnosis"] = {"verdict": f"error: {message}"}
    runs: dict[str, dict] = {}
    sweep = directory / "effect" / "sweep.seq.nrrd"
    start = time.perf_counter()
    runs["a"] = _fit_correct("a", effect_palpations, sweep, depth, directory, [])
    if diagnosis.exists():
        b = _fit_correct("b", effect_palpations, sweep, depth, directory, ["--compensate", str(diagnosis)])
        runs["b"] = b if b["ok"] else {**runs["a"], "refused": True, "refusal": b.get("error"), "as": "a"}
        if b["ok"]:  # --force-compensation applies what --compensate applied: the same fit and correction
            runs["e"] = {**b, "as": "b"}
        else:
            e = _fit_correct(
                "e",
                effect_palpations,
                sweep,
                depth,
                directory,
                ["--compensate", str(diagnosis), "--force-compensation"],
            )
            runs["e"] = e if e["ok"] else {**runs["a"], "refused": True, "refusal": e.get("error"), "as": "a"}
    else:
        runs["b"] = {**runs["a"], "refused": True, "refusal": "no diagnosis", "as": "a"}
        runs["e"] = {**runs["a"], "refused": True, "refusal": "no diagnosis", "as": "a"}
    if kind == "null":
        runs["d"] = {**runs["a"], "as": "a"}
    else:
        runs["d"] = _fit_correct("d", clean_palpations, clean_dir / "sweep.seq.nrrd", depth, directory, [])
    timings["fit_correct_s"] = time.perf_counter() - start
    phantom = effect_info["phantom"]
    face_args = {"lift_mm": 0.0}
    start = time.perf_counter()
    scores: dict[str, dict | None] = {}
    for name in RUNS:
        run = runs[name]
        scores[name] = score_sequence(Path(run["corrected"]), phantom, face_args) if run.get("ok") else None
    scores["uncorrected_effect"] = score_sequence(sweep, phantom, face_args)
    scores["uncorrected_clean"] = score_sequence(clean_dir / "sweep.seq.nrrd", phantom, face_args)
    truth = np.load(clean_dir / "truth.npz")
    scores["segmentation_check"] = score_sequence(clean_dir / "sweep.seq.nrrd", phantom, face_args, truth["imaged"])
    timings["scoring_s"] = time.perf_counter() - start
    row["runs"] = runs
    row["scores"] = scores
    row["clean_sweep_force_range_n"] = clean_info["sweep_force_range_n"]
    row["timings"] = timings
    return row


def _median(values: list[float]) -> float | None:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.median(values)) if values else None


def _summary(rows: list[dict]) -> dict[str, dict]:
    table: dict[str, dict] = {}
    for kind in sorted({r["kind"] for r in rows}):
        chosen = [r for r in rows if r["kind"] == kind]
        costs, shares_b, shares_e, worse, worse_e, costly, null_same, failed = [], [], [], 0, 0, 0, [], 0
        for r in chosen:
            s = r["scores"]
            if any(s.get(k) is None for k in RUNS):
                failed += 1
                continue
            cost = s["d"]["dice_mean"] - s["a"]["dice_mean"]
            area_cost = s["a"]["abs_area_error_pct_mean"] - s["d"]["abs_area_error_pct_mean"]
            costs.append(cost)
            if cost >= 0.01 or area_cost >= 2.0:
                costly += 1
                if abs(cost) > 1e-9:
                    shares_b.append((s["b"]["dice_mean"] - s["a"]["dice_mean"]) / cost)
                    shares_e.append((s["e"]["dice_mean"] - s["a"]["dice_mean"]) / cost)
            if s["b"]["dice_mean"] < s["a"]["dice_mean"] - 0.005:
                worse += 1
            if s["e"]["dice_mean"] < s["a"]["dice_mean"] - 0.005:
                worse_e += 1
            if kind == "null":
                null_same.append(s["b"]["frames_md5"] == s["a"]["frames_md5"])
        table[kind] = {
            "cases": len(chosen),
            "failed": failed,
            "costly": costly,
            "median_cost_dice": _median(costs),
            "median_recovered_b": _median(shares_b),
            "median_recovered_e": _median(shares_e),
            "worse_b": worse,
            "worse_e": worse_e,
            "null_b_equals_a": (f"{sum(null_same)}/{len(null_same)}" if kind == "null" else None),
        }
    return table


def _f(value: object, digits: int = 3) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and abs(value) >= 10**digits:
        return f"{value:.0f}"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) >= 1e-3 or value == 0 else f"{value:.1e}"
    return str(value)


def markdown(rows: list[dict], table: dict, command: str, wall_s: float) -> str:
    lines = [
        "# Compensation on the independent generator's sweeps",
        "",
        f"Command: `{command}`",
        "",
        f"Wall time {wall_s:.0f} s (this invocation; the cases' own times sum to "
        f"{sum(sum(r['timings'].values()) for r in rows):.0f} s, cases run --workers at once). "
        "Runs: (a) effect, no compensation; (b) `--compensate` with the blind diagnosis; "
        "(e) (b) plus `--force-compensation`; (d) the case without the effect. Scores: mean over the sweep's frames "
        "of the segmented lumen against the zero-force truth.",
        "",
        "| kind | cases | failed | costly | median cost (Dice d-a) | median recovered (b) | median recovered (e) "
        "| worse by > 0.005 Dice (b / e) | null: b = a |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for kind, t in table.items():
        lines.append(
            f"| {kind} | {t['cases']} | {t['failed']} | {t['costly']} | {_f(t['median_cost_dice'])} | "
            f"{_f(t['median_recovered_b'])} | {_f(t['median_recovered_e'])} | {t['worse_b']} / {t['worse_e']} | "
            f"{t['null_b_equals_a'] or '-'} |"
        )
    lines += [
        "",
        "| case | kind | hidden | verdict | named | b | e | clamp a/b/e/d | Dice unc. eff / clean | Dice a | b | e | d "
        "| area % a | b | e | d | depth mm a | b | e | d | seg. check Dice | times gen/diag/fit+corr s |",
        "|" + "---|" * 23,
    ]
    for r in rows:
        s, runs, diag = r["scores"], r["runs"], r.get("diagnosis", {})

        def get(name: str, key: str, s: dict = s) -> str:
            return _f(s[name][key]) if s.get(name) else "fail"

        def status(name: str, runs: dict = runs) -> str:
            run = runs[name]
            if run.get("refused"):
                return "refused"
            return "ok" if run.get("ok") else f"fail ({run.get('stage')})"

        clamp = "/".join("y" if runs[n].get("clamped") else "n" for n in ("a", "b", "e", "d"))
        t = r["timings"]
        hidden = ", ".join(f"{k}={_f(v)}" for k, v in r["hidden_parameters"].items() if k != "g_prony_equivalent")
        lines.append(
            f"| {r['case']} | {r['kind']} | {hidden or '-'} | {diag.get('verdict')} | "
            f"{', '.join(diag.get('named') or []) or '-'} | {status('b')} | {status('e')} | {clamp} | "
            f"{get('uncorrected_effect', 'dice_mean')} / {get('uncorrected_clean', 'dice_mean')} | "
            + " | ".join(get(n, "dice_mean") for n in RUNS)
            + " | "
            + " | ".join(get(n, "area_error_pct_mean") for n in RUNS)
            + " | "
            + " | ".join(get(n, "depth_error_mm_mean") for n in RUNS)
            + f" | {get('segmentation_check', 'dice_mean')} | "
            f"{t['generation_s']:.0f}/{t['diagnosis_s']:.0f}/{t['fit_correct_s']:.0f} |"
        )
    errors = [
        (r["case"], n, r["runs"][n].get("stage"), r["runs"][n].get("error") or r["runs"][n].get("refusal"))
        for r in rows
        for n in RUNS
        if not r["runs"][n].get("ok") or r["runs"][n].get("refused")
    ]
    if errors:
        lines += ["", "Refusals and failures (last stderr line):", ""]
        lines += [f"- case {c} ({n}, {stage or 'compensate'}): {message}" for c, n, stage, message in errors]
    return "\n".join(lines) + "\n"


def _usdeform_version() -> str:
    """The usdeform commit the run used (its behaviour, e.g. which verdicts ``--compensate`` accepts, changes)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "python"], capture_output=True, text=True
        ).stdout.strip()
    except OSError:
        return "unknown"
    return head.stdout.strip() + (" (python/ modified)" if dirty else "") if head.returncode == 0 else "unknown"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--cases", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("comp-independent"))
    parser.add_argument("--quick", action="store_true", help="coarse mesh, 40 palpation frames, a 3-3.5 s sweep")
    parser.add_argument("--kinds", default=None, help=f"comma-separated kinds to cycle through (of {', '.join(KINDS)})")
    parser.add_argument("--workers", type=int, default=1, help="cases run at once (processes)")
    parser.add_argument("--fresh", action="store_true", help="rerun cases already in DIR/cases.jsonl")
    args = parser.parse_args(argv)
    if args.cases < 1:
        parser.error("--cases must be at least 1")
    if args.seed < 0:
        parser.error("--seed must be non-negative")
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is an existing file")
    cycle = kinds_to_cycle(parser, args.kinds, DEFAULT_KINDS, KINDS)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    command = "python benches/compensation_independent.py " + " ".join(sys.argv[1:] if argv is None else argv)
    started = time.perf_counter()
    version = _usdeform_version()
    log = out / "cases.jsonl"
    rows: list[dict] = []
    if log.exists() and not args.fresh:
        for line in log.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            same = row.get("seed") == args.seed and row.get("quick") == args.quick
            same = same and "error" not in row and row["case"] < args.cases
            if same and row.get("kind") == cycle[row["case"] % len(cycle)]:
                rows.append(row)
    done = {row["case"] for row in rows}
    log.write_text("".join(json.dumps(row) + "\n" for row in rows))
    todo = [(i, cycle[i % len(cycle)]) for i in range(args.cases) if i not in done]
    failed: list[dict] = []

    def finish(row: dict) -> None:
        with log.open("a") as handle:
            handle.write(json.dumps(row) + "\n")
        if "error" in row:
            print(f"case {row['case']} ({row['kind']}): error {row['error']}", flush=True)
            failed.append(row)
            return
        rows.append(row)
        s = row["scores"]
        dice = " ".join(f"{n} {s[n]['dice_mean']:.3f}" if s.get(n) else f"{n} fail" for n in RUNS)
        print(
            f"case {row['case']} ({row['kind']}): {row['diagnosis'].get('verdict')}, Dice {dice}, "
            f"{sum(row['timings'].values()):.0f} s",
            flush=True,
        )

    if args.workers == 1:
        for index, kind in todo:
            finish(run_case(index, kind, args.seed, args.quick, out))
    else:
        with ProcessPoolExecutor(args.workers) as pool:
            futures = [pool.submit(run_case, i, k, args.seed, args.quick, out) for i, k in todo]
            for future in futures:
                finish(future.result())
    rows.sort(key=lambda r: r["case"])
    wall = time.perf_counter() - started
    table = _summary(rows)
    (out / "benchmark.json").write_text(
        json.dumps(
            {"command": command, "usdeform": version, "wall_s": wall, "per_kind": table, "cases": len(rows)}, indent=1
        )
    )
    used = sorted({str(r.get("usdeform", "not recorded")) for r in rows})
    text = markdown(rows, table, command, wall).replace(
        "\n\nWall time", f"\n\nusdeform {version} now; the cases ran on {', '.join(used)}. Wall time", 1
    )
    if failed:
        text += "\nCases that failed outside usdeform:\n\n" + "".join(
            f"- case {r['case']} ({r['kind']}): {r['error']}\n" for r in failed
        )
    (out / "benchmark.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
