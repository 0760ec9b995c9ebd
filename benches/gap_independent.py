"""The gap diagnosis on palpations from an independent generator (its own FEM engine and B-mode model).

``usdeform.gap.benchmark`` draws its "real" cases from ``usdeform.sim``, the simulator the diagnosis itself
calibrates (scikit-fem P2 Yeoh sections, bonded base, point-scatterer IQ splat). This command writes palpation
recordings with mechanics and imaging written apart from it (the package benches/independent: ``mechanics``,
``imaging``, ``cases``, ``scoring``), diagnoses each from its PLUS sequence file alone (``usdeform.gap.diagnose``)
and scores the verdicts. Nothing from ``usdeform.sim`` or ``usdeform.gap`` is used except ``diagnose``; the files
are written with ``usdeform.recording`` and ``usdeform.io``.

The follow-up loop: where round 0's diagnosis asks for more (its record_next.json), the generator records it for
the same hidden effect and phantom (``independent.follow_up.record_follow_up``) and the diagnosis of all the case's
recordings is round 1, scored as round 0 (``--no-follow-up``: round 0 only).

Mechanics (``mechanics.solve_phantom``): a 2-D plane-strain total-Lagrangian finite-element model in NumPy/SciPy
on a structured, graded mesh of bilinear quadrilaterals (Q4; ~1-1.3 mm under the probe, coarser towards the sides
and the base). Material: a compressible Demiray (exponential, Fung-like) law
``W = mu / (2 b) (exp(b (I1 - 3 - 2 ln J)) - 1) + lambda / 2 (ln J)^2`` (strain stiffening b 0.3-3, initial
shear modulus mu 10-40 kPa, Poisson's ratio 0.45-0.49), the shear part integrated at 2x2 Gauss points and the
volumetric part at the element centre (selective reduced integration against locking). The vessel is a
circular, very soft (0.005-0.05 of mu) and compressible (nu 0.3) neo-Hookean inclusion assigned per Gauss
point. The probe face (37.5-48 mm) is rigid, in sticking contact: a surface node touches when it would cross the
face (flat, tilted or an arc), is placed on it and then moves with it; a flat level face bonds all its nodes at
first contact. The rest of the surface is free; the base is a roller (vertical fixed, one node pinned laterally),
where usdeform.sim bonds it. Newton-Raphson with line search in adaptive probe-travel steps up to a force cap, a
step solved again while new nodes touch. The force is the plane-strain reaction along the probe axis (N/mm) times
an effective elevation width (20-30 mm, more than the array's ~10 mm to stand for the 3-D spread of the load;
gives 1-4 N/mm near 5 mm).

Imaging (``imaging.Scanner``, ``Texture``, ``Renderer``): a reflectivity texture on a fine grid (0.05 mm lateral,
0.025 mm axial) in the *undeformed* tissue: Gaussian amplitudes with a smooth density variation, sparse bright
points, an anechoic lumen, a brighter ~1 mm wall ring and up to two bright fibres. For a frame, each sample of
a fine image grid (probe frame; depth 0 is the probe face) is placed in the tissue by the face's pose, mapped back
to its reference position by a fixed-point inversion of the FEM displacement, jittered by a smooth random field
(0.01-0.02 mm rms, new for every frame), the texture is sampled there (``cv2.remap``), convolved with an RF pulse
(axially a Gaussian-windowed cosine at 5-7.5 MHz, c = 1540 m/s; laterally a Gaussian), attenuated, given
band-limited electronic noise, time-gain compensated, envelope-detected (Hilbert transform along depth),
log-compressed and area-resampled to the pixels. usdeform.sim instead splats point scatterers with a Gaussian IQ
PSF.

Timeline: force-controlled palpation from contact (0.2-0.5 N) up at 3-6 N/s to 8-20 N, hold 1.5-3 s, down;
lambda(t) by inverting the FEM force curve on a 1 kHz clock, with robot position ripple (0.01-0.05 mm) and
force-sensor noise (0.02-0.06 N); 20-30 fps (at most 120 frames kept), millisecond timestamp jitter.

Hidden kinds (own implementations; ranges and why):

- ``null``: none.
- ``image_latency``: frames show the tissue at t - 0.05-0.15 s.
- ``force_sensor_error``: bias +-0.3-1 N and drift +-0-0.02 N/s on the logged force.
- ``viscoelasticity``: a standard linear solid under force control: F = F_e(lambda) + q, dq/dt = -q / tau +
  g dF_e/dt (g 0.15-0.45, tau 0.5-3 s), so lambda creeps during the hold.
- ``force_latency``: the logged force is the force at t - 0.05-0.25 s (an F/T sensor's filters, its driver's
  buffering and message transport, stamped on arrival).
- ``force_sensor_lag``: the logged force is the force through a first-order low-pass, time constant 0.05-0.3 s
  (cut-off 0.5-3 Hz, as set on F/T sensors to quiet the probe's vibration), exact on the 1 kHz clock.
- ``pose_latency``: the poses and the probe displacement are those at t - 0.05-0.2 s (robot state published at
  100-500 Hz over a network or an optical tracker's latency, stamped on arrival); force and images on time.
- ``force_sensor_drift``: logged force (1 + gain error) F + bias + drift t: gain +-3-10 % (calibration of low-cost
  F/T sensors, a wrong tool compensation), bias +-0.1-0.5 N, drift +-0.02-0.1 N/s from the recording's start (a
  strain-gauge sensor warming up; large, so it shows in a 5-15 s palpation); unlike ``force_sensor_error`` the
  error grows with the load.
- ``surface_inclination``: the tissue surface inclined +-4-12 deg under a level probe that travels vertically
  (along its axis): solved in the tissue's frame with the face tilted and travelling at that angle from the
  normal; one edge touches first; poses level (body surfaces under a probe, e.g. neck or forearm, slope by this
  much; a surface normal estimated from a depth camera is off by several degrees).
- ``probe_tilt``: the probe tilted +-4-12 deg in the image plane over a level surface, travelling along the
  surface normal; poses carry the tilt (same reasons, seen from the robot's side).
- ``out_of_plane_drift``: the image plane moves in elevation by +-0.2-1.5 mm over the recording, a share (0-1)
  with time and the rest with the indentation (tissue slipping sideways under a not exactly normal load,
  breathing; freehand strain imaging reports motions of the order of the beam's elevation width). The texture
  gets elevation slices (independent scatterers at sigma / 2 spacing, the structure shared) summed with a
  Gaussian elevation beam profile of FWHM 1-2 mm (linear arrays near their elevation focus) at the current
  position.
- ``sound_speed_mismatch``: tissue sound speed 1450-1520 or 1560-1600 m/s (fat ~1450-1480, muscle ~1580-1600 m/s;
  within 20 m/s of 1540 left out as no mismatch), the scanner converting with 1540 m/s: displayed depth is true
  depth x 1540 / c, the pulse keeps its displayed length (c / 1540 as long in the tissue), attenuation on the true
  depth.
- Tissue effects, in the FEM (not in the 24-case cycle, which keeps its seeds' recordings: run them with
  ``--kinds``; the texture is unchanged). Each reached the force cap in 30 drawn cases (20 on the coarse mesh, 10
  on the fine). At the softest corner (mu 10-13 kPa, b < 1, a 7 mm-deep vessel, lumen 0.005 mu) the thickest,
  softest layer or sliding contact lets the soft inclusion collapse (J -> 0) at 13.5-13.8 mm, just short of the
  14 mm travel limit where the solve without the effect stops; the solve ends there and the peak force is
  lowered as for any soft phantom. The ranges are not narrowed for it: the inclusion limits, not the effect.
- ``soft_layer`` (scored by ``layered_tissue``): a subcutaneous layer 3-12 mm thick at the top of the block with
  0.15-0.5 of the tissue's shear modulus (an element whose centroid lies above the layer depth gets it; Lame's
  lambda scales with it, same Poisson's ratio and stiffening). Subcutaneous fat measured by standardised ultrasound
  is ~3-10 mm per site in normal-weight adults (eight-site sums 12-245 mm from lean to obese: Störchle et al.,
  Ultrasound Med Biol 2017, Sci Rep 2018); compression of the gluteal region with ultrasound gives subcutaneous
  tissue a Young's modulus of ~26 kPa against ~62 kPa for the muscle below at low loads (Isogai et al., J Phys
  Ther Sci 2022: ratio ~0.4), and fat is softer still over stiffer glands or tense muscle.
- ``frictionless_contact`` (scored by ``sliding_contact``): the face slides freely (a switch, nothing drawn): it
  constrains only the normal (depth) displacement of the surface nodes it touches, the lateral one is free; a node
  sliding past the face's edge is held at its corner, and tissue drawn in beside the face meets the probe's side
  wall (held laterally there). A film of coupling gel lubricates the probe on the skin (thick films slide in the
  mixed or hydrodynamic regime of a Stribeck curve: Persson et al., Tribol Lett 2013), while water alone or a
  drying film raises the skin's friction (Adams et al., Tribol Lett 2007): a gel-coupled probe can slip, and the
  sticking contact above is the other limit. With the tissue's Poisson's ratio 0.45-0.49 normal load and
  tangential slip couple weakly ((1 - 2 nu) small), so the signature is small: ~0.1 mm of lateral surface
  motion, the force within ~1 %.
- ``lumen_pressure`` (scored by ``lumen_pressure``): a uniform pressure p = 0.08-0.3 mu (0.8-12 kPa, 6-90 mmHg for mu
  10-40 kPa) in the vessel, applied before contact and held constant: the stress -p I of a fluid in the (soft,
  kept) inclusion, i.e. nodal forces on its boundary, normal to the deformed boundary (a follower load). The
  surface bulges over the vessel; the face first touches the bulge's top (``lambda`` 0 and the poses there),
  the contact spreads from it, and tissue drawn in beside the face meets the probe's side wall. Venous pressures
  are ~0-15 mmHg (central), more in a dependent limb or under a Valsalva manoeuvre (the force a probe needs to
  collapse the internal jugular vein tracks the central venous pressure: Jaffe et al., quantitative compression
  ultrasound); arterial 80-120 mmHg (11-16 kPa). With the shear modulus 10-40 kPa the range spans a distended vein
  to a low arterial pressure on the soft, compressible lumen.
- ``convex_probe_face`` (out of library): the face a circular arc of radius 40-80 mm (the curvature of convex
  probes), touching at its apex first; nodes under the arc touch as it reaches them; the image stays the linear
  array's, its depth 0 at the apex (an array behind a standoff of tissue's sound speed, the rows above the apex
  cropped).
- ``gain_drift`` (out of library): the scanner's gain drifts linearly by +-4-10 dB over the palpation (automatic
  gain optimisation or a gain change during the recording).
- ``acoustic_shadow`` (out of library): a calcification (radius 0.8-2 mm, 5-12 mm deep, 10-13 mm beside the
  vessel) 12-20 dB brighter than the tissue, losing 10-25 dB (two-way) across its diameter, so the scan lines
  below it are darkened (calcified plaque or nodes, small: partial shadows); it moves with the tissue, the
  shadow along the beam.
Outside the 24-case cycle too (run with ``--kinds``; they leave the cycle's recordings as they are):
- ``image_clock_drift`` (scored by ``image_latency``): a frame stamped t shows the tissue at t - d(t), d growing
  linearly from d0 = 0-0.03 s at the first frame to d0 + 0.08-0.25 s at the last (mean 0.04-0.155 s); force and
  poses on time. The scanner's and the robot PC's clocks are not synchronised (no PTP): an offset, and a frame
  grabber or streaming queue read more slowly than it fills (frames stamped on arrival) lets the delay build up; a
  crystal's rate error alone (tens of ppm) would add under 1 ms over a palpation, so the growth stands for the
  buffering.
- ``stiff_inclusion`` (out of library): a disc of radius 2.5-6 mm with 4-10x the tissue's shear modulus (the same
  Demiray law, stiffening and Poisson's ratio; Lame's lambda scales; assigned per Gauss point, the fine mesh
  reaching 6 mm below it), 5-15 mm (wall to edge) beside or below the vessel (direction uniform from straight
  below to level with it, either side), drawn again until it lies in the image at rest (1 mm inside its sides and
  bottom), which favours the smaller radii and gaps (medians 3.6 and 7.6 mm). Its scatterers are the tissue's:
  isoechoic in half the cases, else 1-3 dB brighter. Fibrous tissue and invasive carcinomas are several to over
  ten times stiffer than fat and glandular tissue (Krouskop et al., Ultrason Imaging 1998), and many solid nodules
  and fibrotic regions are isoechoic in B-mode (what strain elastography finds them by): a local low-strain
  region, the force ~3 % higher in the case checked.
- ``breathing_motion`` (out of library): the tissue block moves axially with its base, b(t) = A sin(2 pi f t + phi)
  (positive away from the probe; A 0.3-1.2 mm, f 0.2-0.33 Hz, i.e. 12-20 breaths/min, an adult's resting rate; phi
  uniform), rigidly (quasi-static at these rates), so the tissue's state is the FEM's at the indentation lambda - b.
  The robot keeps force control: its travel lambda is the feedforward indentation of the target force (as for the
  other kinds) plus the ripple plus b through the force loop's answer, a first-order low-pass of bandwidth 0.5-2 Hz (a
  nuisance drawn with it: compliant force loops, tuned soft for a stable contact), in steady state. The indentation
  keeps the high-passed rest (amplitude A f / sqrt(f^2 + f_c^2), 0.03-0.56 mm in 3000 draws, median 0.16 mm), so the
  logged force oscillates (the rest times the tissue's stiffness, 1-4 N/mm: a few hundredths of a newton to ~2 N,
  growing with the load) and the logged travel with ~A; a negative indentation is a lift-off over a film of gel (force
  0, an anechoic gel gap at the top of the image); the peak force is lowered if the peak plus the rest would leave the
  FEM's curve. Superficial tissue at the neck, upper chest or groin rises and falls with respiration by a fraction of
  a millimetre to about a millimetre (over the abdomen by several, left out).

Scoring: a verdict explained, explained_in_part or ambiguous attributes; the effects it names are diagnosis.json's
``named`` (two when ambiguous; ``a+b`` a pair). An in-library case is correct when a named entry consists of
effects that count for its kind (top-1; one of an ambiguous verdict's two will do): each its own library effect,
and the equivalences ``force_sensor_lag`` -> ``force_latency`` (a first-order lag of time constant tau delays a
slowly varying signal by tau: F(t - tau) to first order), ``pose_latency`` -> ``image_latency`` and/or
``force_latency`` (against a late pose stream the images and the force both lead), ``force_sensor_drift`` ->
``force_sensor_error`` (an error of the force sensor's reading), ``surface_inclination`` -> ``probe_tilt`` (only
the relative tilt of face and surface enters the contact), ``out_of_plane_drift`` -> ``out_of_plane_motion``,
``image_clock_drift`` -> ``image_latency`` (its nearest form: a constant delay, the drift's mean). For
nulls and out-of-library kinds any attribution is a false attribution. benchmark.md gives top-1 over in-library
cases, the false attribution rate over nulls and out-of-library cases, a per-kind table and the confusion matrix
(hidden kind x verdict x named effects).

Cases: case i's kind is ``cases.CYCLE[i % 24]`` (each kind at least once in 24 cases, 6 nulls), or cycles
through ``--kinds``. Generator version 2 (version 1 had 4 kinds in a cycle of 6); for the kinds of version 1 a
seed draws the same recordings, so cases 0, 1, 3, 4 and 5 are version 1's.

    python benches/gap_independent.py --cases 24 --seed 1 --out gap-independent
    python benches/gap_independent.py --cases 2 --quick --no-diagnose --png   # generator check only
    python benches/gap_independent.py --cases 3 --kinds probe_tilt,gain_drift --out DIR

Seeds: ``SeedSequence(seed)`` spawns a generation and a diagnosis stream; case i takes child i of each, so the
same seed gives the same recordings whatever ``--cases``. FEM solves are cached in DIR/fem_cache. Rows already
in DIR/cases.jsonl (same seed, mode, kinds and version) are kept and their cases skipped unless ``--fresh``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from independent.cases import CYCLE, KINDS, generate_case, kinds_to_cycle
from independent.mechanics import GENERATOR_VERSION
from independent.scoring import fmt, score, summary_markdown


def _diagnosed(diagnose, paths: list[Path], seed: int, workers: int | None) -> tuple[dict, list]:
    """diagnosis.json of ``paths`` and its follow-up protocol (a failed diagnosis is an outcome: its verdict says
    the error, and it asks for nothing)."""
    try:
        diagnosis = diagnose(paths, seed=seed, progress=False, workers=workers)
    except Exception as exc:
        return {"verdict": f"error: {type(exc).__name__}: {exc}", "effects": [], "measures": []}, []
    return diagnosis.to_json(), list(diagnosis.follow_up)


def _follow_up_round(diagnose, drawn: dict, asked: list, first: list[Path], directory: Path, seed: int, workers):
    """Round 1 of a case: what round 0's record_next.json asks for, recorded by the independent generator
    (``independent.follow_up.record_follow_up``) for the same hidden effect and phantom, and the diagnosis of all
    the case's recordings. Returns the added recordings' record and (as ``result``) round 1's diagnosis.json."""
    from usdeform.gap.follow_up import write_record_next

    if not asked:
        return {"follow_up": {"asked": [], "recordings": 0, "palpations": 0, "seconds": 0.0}}
    from independent.follow_up import record_follow_up

    start = time.perf_counter()
    plan = directory / "record_next.json"
    write_record_next(plan, asked)
    try:
        recorded = record_follow_up(drawn, plan, directory / "follow_up")
    except ValueError as exc:  # a kind or parameter the generator cannot record: round 1 is round 0
        return {"follow_up": {"asked": [e.kind for e in asked], "error": str(exc), "recordings": 0, "seconds": 0.0}}
    paths = [Path(item["path"]) for item in recorded]
    result, _ = _diagnosed(diagnose, [*first, *paths], seed, workers)
    (directory / "diagnosis_round1.json").write_text(json.dumps(result, indent=1))
    added = {
        "asked": [entry.kind for entry in asked],
        "recordings": len(paths),
        "palpations": sum(item["kind"] != "known_weight" for item in recorded),
        "seconds": float(sum(item.get("seconds", 0.0) for item in recorded)),
    }
    return {"follow_up": added, "round1_s": time.perf_counter() - start, "result": result}


def _loop_markdown(rows: list[dict], command: str) -> str:
    """Round 1's summary (the same tables as round 0's) and what the follow-up added per case."""
    after = [{**row, **row.get("round1", {})} for row in rows]
    added = [row.get("follow_up", {}) for row in rows]

    def spread(key: str) -> str:
        values = [float(item.get(key, 0.0)) for item in added]
        return f"{np.median(values):.3g} / {max(values):.3g}" if values else "-"

    text = summary_markdown(after, command).replace(
        "# Gap diagnosis on the independent generator", "# Round 1: after the follow-up", 1
    )
    return (
        "\n\n## The follow-up loop\n\n| added per case | median / max |\n|---|---|\n"
        f"| cases followed up | {sum(bool(item.get('asked')) for item in added)} of {len(rows)} |\n"
        f"| recordings | {spread('recordings')} |\n| palpations | {spread('palpations')} |\n"
        f"| seconds of recording | {spread('seconds')} |\n\n" + text.replace("\n# ", "\n## ")
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--cases", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("gap-independent"))
    parser.add_argument("--quick", action="store_true", help="coarse mesh, 40 frames, 4 fine samples per pixel")
    parser.add_argument("--no-diagnose", action="store_true", help="generate the recordings only")
    parser.add_argument("--png", action="store_true", help="write 5 frames per case as PNG")
    parser.add_argument("--fresh", action="store_true", help="rerun cases already in DIR/cases.jsonl")
    parser.add_argument("--workers", type=int, default=None, help="processes for the diagnosis's FEM solves")
    parser.add_argument(
        "--no-follow-up", action="store_true", help="score round 0 only (no recordings of record_next.json)"
    )
    parser.add_argument("--kinds", default=None, help=f"comma-separated kinds to cycle through (of {', '.join(KINDS)})")
    args = parser.parse_args(argv)
    cycle = kinds_to_cycle(parser, args.kinds, CYCLE, KINDS)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    command = "python benches/gap_independent.py " + " ".join(sys.argv[1:] if argv is None else argv)
    generation_root, diagnosis_root = np.random.SeedSequence(args.seed).spawn(2)
    generation = generation_root.spawn(args.cases)
    diagnosis_seeds = [int(s.generate_state(1)[0]) for s in diagnosis_root.spawn(args.cases)]
    log = out / "cases.jsonl"
    rows: list[dict] = []
    if log.exists() and not args.fresh and not args.no_diagnose:
        for line in log.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            same = row.get("seed") == args.seed and row.get("quick") == args.quick
            same = same and row.get("kind") == cycle[row["case"] % len(cycle)]
            if same and row.get("version") == GENERATOR_VERSION and row["case"] < args.cases:
                rows.append(row)
    done = {row["case"] for row in rows}
    if not args.no_diagnose:
        log.write_text("".join(json.dumps(row) + "\n" for row in rows))
    for index in range(args.cases):
        if index in done:
            continue
        kind = cycle[index % len(cycle)]
        directory = out / f"case_{index:03d}"
        start = time.perf_counter()
        drawn = generate_case(
            kind, np.random.default_rng(generation[index]), directory, out / "fem_cache", args.quick, args.png
        )
        generation_s = time.perf_counter() - start
        print(f"case {index} ({kind}): generated in {generation_s:.0f} s {fmt(drawn['hidden_parameters'])}", flush=True)
        if args.no_diagnose:
            continue
        from usdeform.gap import diagnose  # only when diagnosing: generating needs usdeform.io and .recording

        start = time.perf_counter()
        first = [directory / "palpation.seq.nrrd"]
        result, asked = _diagnosed(diagnose, first, diagnosis_seeds[index], args.workers)
        diagnosis_s = time.perf_counter() - start
        (directory / "diagnosis.json").write_text(json.dumps(result, indent=1))
        loop: dict = {}
        if not args.no_follow_up:
            loop = _follow_up_round(diagnose, drawn, asked, first, directory, diagnosis_seeds[index], args.workers)
            loop["round1"] = score(kind, loop.pop("result", result))
        row = {
            "case": index,
            "seed": args.seed,
            "quick": args.quick,
            "version": GENERATOR_VERSION,
            "kind": kind,
            "hidden": None if kind == "null" else kind,
            **drawn,
            **score(kind, result),
            "generation_s": generation_s,
            "diagnosis_s": diagnosis_s,
            **loop,
        }
        rows.append(row)
        with log.open("a") as handle:
            handle.write(json.dumps(row) + "\n")
        print(
            f"case {index} ({kind}): {row['verdict']}, named {', '.join(row['named']) or '-'}, top {row['top']} "
            f"(shrink {fmt(row['top_shrink'], 2)}), "
            f"diagnosed in {diagnosis_s:.0f} s",
            flush=True,
        )
    if args.no_diagnose:
        return
    rows.sort(key=lambda r: r["case"])
    text = summary_markdown(rows, command)
    if any("round1" in row for row in rows):
        text += _loop_markdown(rows, command)
    (out / "benchmark.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
