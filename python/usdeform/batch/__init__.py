"""Cohorts on a Dask cluster: fit, correct and reconstruct the recordings of many subjects.

Needs the optional extra ``pip install 'usdeform[cluster]'`` (Dask distributed, tqdm; bokeh for the
dashboard). Reading and validating manifests works without it.

Command line::

    usdeform batch MANIFEST --out DIR [--scheduler ADDRESS] [--workers N] [--kernel-threads T] [--retries R]

Without ``--scheduler`` a local cluster of ``N`` worker processes (default: one per core) with one
task thread each runs the tasks; each worker's compiled kernels use ``T`` threads (default: cores /
workers, set through ``RAYON_NUM_THREADS``), so the workers together use the machine's cores once.
With ``--scheduler tcp://HOST:8786`` the tasks go to a running cluster (start its workers with
``RAYON_NUM_THREADS=T dask worker tcp://HOST:8786 --nthreads 1``); the workers and the client
must all see the manifest's recordings and DIR under the same paths (one machine, or a shared file
system): tasks carry paths, never recordings. Python::

    from usdeform.batch import read_manifest, run_batch, batch_client, submit_batch
    result = run_batch(read_manifest("cohort.toml"), "out")          # records, results.json path, counts
    with batch_client("tcp://host:8786") as client:                  # or futures, on your own client
        futures = submit_batch(client, read_manifest("cohort.toml"), "out")

Manifest (TOML)
---------------
Relative paths are relative to the manifest's folder. ``[options]`` sets defaults for every
subject; a subject's ``options`` table overrides them. The options are those of ``usdeform fit`` and
``usdeform correct`` (:class:`usdeform.pipeline.PipelineSettings`, which both run through) with the same
defaults and checks, named as their flags with ``_`` for ``-`` (``--spacing``: ``spacing_mm``), plus which
outputs to write (``report``, ``volume``, ``coverage``) and the diagnosis' seed::

    [options]
    flexible_layer_mm = 60.0       # required (here or per subject): compressible tissue under the probe, mm
    method = "recommended"         # "recommended" | "paper" (usdeform.fitting.FIT_METHODS); the next five
                                   # change single settings of it (omitted: the method's)
    # basis = "bspline:8x8"        # "quadratic" or "bspline:NXxNY", e.g. "bspline:8x6"
    # coupling = "stiffness"       # "stiffness" (h = F/k, the paper) | "force" (the force-based baseline)
    # integration = "displacement" # "force" (the paper) | "displacement"
    # wall = "auto"                # vessel wall as observations: "auto" | "require" | "off"
    # anchor = "vessel"            # "vessel" (collapse follows each frame's lumen) | "image"
    solver = "exact"               # "exact" | "adam" (quadratic basis, anchor "image", only)
    # smoothness = 1e-4            # B-spline penalty weight; omitted: chosen by cross-validation
    wall_weight = 1.0              # weight of the vessel wall's mean squared error against the tracks'
    report = false                 # also write the fit's report (usdeform fit --report): SUBJECT/fit-report/
    stiffness_source = "auto"      # each sweep frame's stiffness: "auto" | "interpolated" | "sweep"
    clamp_force = false            # clamp forces outside the model's fitted range into it (default: refuse them)
    volume = true                  # also compound each corrected sweep into a volume
    coverage = false               # also write each volume's coverage (weight) volume (needs volume = true)
    spacing_mm = 0.5               # voxel size, mm
    interpolation = "nearest"      # "nearest" | "linear"
    compounding = "mean"           # "mean" | "max" | "latest"
    fill_holes = "off"             # "off" or one PLUS HoleFillingElement step: "gaussian" | "gaussian_accumulation"
                                   # | "distance_weight_inverse" | "nearest_neighbor" | "stick"
    voxel_type = "float32"         # "float32" | "uint8" (as PLUS writes)
    max_gib = 4.0                  # memory limit of one volume, GiB
    compression_level = 1          # compression level of the volume files: 1 (fastest, ISA-L) to 9 (smallest,
                                   # zlib); not a reason to redo a finished sweep
    diagnosis_seed = 0             # seed of the gap diagnosis' bootstrap
    # compensate = "diag/diagnosis.json"  # undo the effects this diagnosis ('usdeform diagnose') names on the
                                   # palpations and sweeps first, as fit/correct --compensate (an input of
                                   # the fit and the sweeps: a new diagnosis there redoes them)
    force_compensation = false     # compensate even where the diagnosis does not support it, as
                                   # --force-compensation (true needs compensate)

    [[subjects]]
    id = "patient-001"             # letters, digits, '.', '_', '-': names the output folder
    palpations = ["p001/palpation-1.mha", "p001/palpation-2.seq.nrrd"]   # at least one
    sweeps = ["p001/sweep-1.mha", "p001/sweep-2.mha"]                    # optional
    diagnosis = true               # optional: true = diagnose the palpations, or a list of recordings
    options = { flexible_layer_mm = 45.0 }

Manifest (CSV)
--------------
One row per subject under a header row. Columns ``subject`` and ``palpations`` are required;
``sweeps`` and ``diagnosis`` are optional; any option above may be a column (an empty cell takes
the default). Lists of paths are separated by ``;``; ``diagnosis`` is empty or false (none), true
(the palpations) or a list of paths::

    subject,palpations,sweeps,diagnosis,flexible_layer_mm,basis
    patient-001,p001/palpation-1.mha;p001/palpation-2.mha,p001/sweep-1.mha,true,60,quadratic
    patient-002,p002/palpation-1.mha,p002/sweep-1.mha;p002/sweep-2.mha,,45,bspline:8x6

A malformed manifest is rejected before anything runs, with the line (CSV) or field (TOML) named; so
is a ``compensate`` diagnosis that is missing or that ``--compensate`` would refuse (verdict not
"explained" or "explained_in_part", effect not significant, unless ``force_compensation = true``; an
effect of the tissue itself), with the subject, the option and the file named.

Outputs and the results manifest
--------------------------------
Per subject ``DIR/SUBJECT/model.json`` (the fit of all its palpations, as ``usdeform fit``; with
``report = true`` also ``DIR/SUBJECT/fit-report/report.html`` and ``report.json``, as ``--report``), per
sweep ``DIR/SUBJECT/NAME.corrected.seq.nrrd``, ``DIR/SUBJECT/NAME.volume.nrrd`` and with ``coverage = true``
``DIR/SUBJECT/NAME.coverage.nrrd`` (as ``usdeform correct --volume --coverage``; NAME is the sweep's file name
without its suffix) and ``DIR/SUBJECT/diagnosis.json``, ``record_next.json`` and ``report.html``
(as ``usdeform diagnose`` writes them). Every file is written to a temporary file and renamed, so a killed
worker never leaves a half-written output (its temporary file is removed when the task is retried).

``DIR/results.json`` is written (atomically) as tasks finish: ``{"format": "usdeform-batch-results",
"version": 1, "manifest", "out", "updated", "summary": {"done", "failed", "skipped", "pending",
"reused"}, "tasks": [...]}``, one record per task with ``id`` (``SUBJECT/fit``,
``SUBJECT/sweep/NAME``, ``SUBJECT/diagnosis``), ``kind``, ``subject``, ``status`` ("done", "failed":
``error`` says why in one line, "skipped": the fit it needs failed, "pending"), ``reused``,
``started``, ``seconds``, ``worker``, ``inputs`` and ``outputs`` (path, size, mtime_ns), ``options``
and ``details`` (stiffness, loss and the report's warnings of a fit, frames and force range of a
sweep, verdict of a diagnosis; with ``compensate``, a fit's and a sweep's ``compensation``: the
diagnosis, its verdict, effects and parameters, ``forced`` and the ``notes`` saying what changed). A
recording that fails does not stop the batch. Run the same command again to finish a batch: a task
is reused when its last record is done with the same options and inputs (size and modification time)
and its outputs are unchanged; anything else (failed tasks, changed inputs or options, a refitted
model for its sweeps, a new diagnosis to compensate) runs again.
"""

from __future__ import annotations

from .manifest import Manifest, Options, Subject, read_manifest
from .runner import BatchResult, batch_client, dashboard_link, read_results, run_batch, submit_batch
from .tasks import TaskSpec, plan_tasks, run_task

__all__ = [
    "BatchResult",
    "Manifest",
    "Options",
    "Subject",
    "TaskSpec",
    "batch_client",
    "dashboard_link",
    "plan_tasks",
    "read_manifest",
    "read_results",
    "run_batch",
    "run_task",
    "submit_batch",
]
