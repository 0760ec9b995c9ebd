"""The units of work of a batch: fit a subject's position, reconstruct one sweep, diagnose the gap.

:func:`plan_tasks` turns a manifest into :class:`TaskSpec` items (plain data: paths, options, the
task it depends on). :func:`run_task` executes one of them where it is called (on a Dask worker in a
batch) and returns its record, a small JSON-able dict: ``id``, ``kind``, ``subject``, ``status``
("done", "failed" or "skipped"), ``error`` (one line, or None), ``reused`` (True when a previous run's
outputs were still valid), ``started`` (UTC, ISO 8601), ``seconds``, ``worker`` (host:pid),
``inputs`` and ``outputs`` (each ``{"path", "size", "mtime_ns"}``), ``options`` and ``details``.

Errors caused by the recording (any :class:`~usdeform.UsdeformError`, a missing or unreadable file)
make a "failed" record and do not stop the batch; any other exception propagates so that Dask retries
the task. A task whose previous record is "done", with the same options, the same inputs (size and
modification time) and its outputs as they were written, is not run again.
"""

from __future__ import annotations

import datetime
import json
import os
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from ..errors import UsdeformError
from . import stages
from .manifest import Manifest, Options, Subject, recording_name

__all__ = ["TaskSpec", "one_line", "plan_tasks", "run_task", "task_record"]

TaskKind = Literal["fit", "sweep", "diagnosis"]
# Failures that are the input's own: retrying elsewhere would fail the same way.
_INPUT_FAILURES = (UsdeformError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)


@dataclass(frozen=True)
class TaskSpec:
    """One unit of work: ``id`` (``SUBJECT/fit``, ``SUBJECT/sweep/NAME``, ``SUBJECT/diagnosis``), the
    recordings it reads (a fit's palpations, a sweep's one sweep, the recordings to diagnose) and its
    outputs (absolute paths), the subject's options, the id of the task whose record it needs (the
    fit, for a sweep) and, for a sweep, the ``model`` file that fit writes."""

    id: str
    kind: TaskKind
    subject: str
    recordings: tuple[Path, ...]
    outputs: tuple[Path, ...]
    options: Options
    depends_on: str | None = None
    model: Path | None = None

    @property
    def compensated_diagnosis(self) -> Path | None:
        """The diagnosis whose effects a fit or a sweep undoes (the ``compensate`` option; None: none)."""
        return None if self.kind == "diagnosis" else self.options.compensate

    @property
    def inputs(self) -> tuple[Path, ...]:
        """Every file the outputs depend on, in this order: the recordings, the model and the compensated
        diagnosis (fingerprinted: a change of any of them, e.g. a new diagnosis, runs the task again)."""
        return (*self.recordings, *(path for path in (self.model, self.compensated_diagnosis) if path is not None))

    def option_values(self) -> dict[str, Any]:
        """The options this task's outputs depend on (compared on a rerun)."""
        if self.kind == "fit":
            return self.options.fit_options()
        if self.kind == "sweep":
            return self.options.reconstruction_options()
        return {"diagnosis_seed": self.options.diagnosis_seed}


def _subject_tasks(subject: Subject, folder: Path) -> list[TaskSpec]:
    model = folder / "model.json"
    report = (folder / "fit-report" / "report.html", folder / "fit-report" / "report.json")
    fit_outputs = (model, *report) if subject.options.report else (model,)
    fit = TaskSpec(f"{subject.id}/fit", "fit", subject.id, subject.palpations, fit_outputs, subject.options)
    tasks = [fit]
    for sweep in subject.sweeps:
        name = recording_name(sweep)
        outputs: tuple[Path, ...] = (folder / f"{name}.corrected.seq.nrrd",)
        if subject.options.volume:
            outputs += (folder / f"{name}.volume.nrrd",)
        if subject.options.coverage:
            outputs += (folder / f"{name}.coverage.nrrd",)
        task_id = f"{subject.id}/sweep/{name}"
        tasks.append(TaskSpec(task_id, "sweep", subject.id, (sweep,), outputs, subject.options, fit.id, model))
    if subject.diagnosis:
        diagnosis = (folder / "diagnosis.json", folder / "record_next.json", folder / "report.html")
        tasks.append(
            TaskSpec(f"{subject.id}/diagnosis", "diagnosis", subject.id, subject.diagnosis, diagnosis, subject.options)
        )
    return tasks


def plan_tasks(manifest: Manifest, out_dir: str | Path) -> list[TaskSpec]:
    """The tasks of ``manifest`` with their outputs under ``out_dir`` (absolute): per subject
    ``SUBJECT/model.json`` (and ``SUBJECT/fit-report/report.html`` and ``report.json`` with the
    ``report`` option), ``SUBJECT/NAME.corrected.seq.nrrd``, ``SUBJECT/NAME.volume.nrrd`` (``volume``
    option) and ``SUBJECT/NAME.coverage.nrrd`` (``coverage`` option) per sweep, ``SUBJECT/diagnosis.json``
    (with ``record_next.json`` and ``report.html``).
    A fit comes before its sweeps."""
    out = Path(out_dir).resolve()
    return [task for subject in manifest.subjects for task in _subject_tasks(subject, out / subject.id)]


def _fingerprint(path: Path) -> dict[str, Any]:
    status = path.stat()
    return {"path": str(path), "size": status.st_size, "mtime_ns": status.st_mtime_ns}


def _fingerprints(paths: Sequence[Path]) -> list[dict[str, Any]] | None:
    """The fingerprints of ``paths``, or None if one of them is missing."""
    try:
        return [_fingerprint(path) for path in paths]
    except OSError:
        return None


def _still_valid(task: TaskSpec, previous: dict[str, Any] | None) -> bool:
    """Whether ``previous`` (the last run's record of this task) is done with what is on disk now."""
    if previous is None or previous.get("status") != "done":
        return False
    same_options = json.dumps(previous.get("options"), sort_keys=True) == json.dumps(
        task.option_values(), sort_keys=True
    )
    return (
        same_options
        and previous.get("inputs") == _fingerprints(task.inputs)
        and previous.get("outputs") == _fingerprints(task.outputs)
    )


def _remove_partial_outputs(task: TaskSpec) -> None:
    """Remove temporary files an earlier attempt left when its worker died mid-write (``atomic_output``
    names them ``.NAME.*.part`` beside the output; only this task writes NAME)."""
    for output in task.outputs:
        for partial in output.parent.glob(f".{output.name}.*.part"):
            partial.unlink(missing_ok=True)


def _reconstruct(task: TaskSpec) -> dict[str, Any]:
    """The task's sweep corrected with its fit's model (and compounded with the ``volume`` option, its coverage
    written with the ``coverage`` option)."""
    (sweep,) = task.recordings
    assert task.model is not None  # plan_tasks gives each sweep its fit's model
    volume = task.outputs[1] if task.options.volume else None
    coverage = task.outputs[2] if task.options.coverage else None
    return stages.reconstruct_sweep(sweep, task.model, task.options, task.outputs[0], volume, coverage)


def _diagnose(task: TaskSpec) -> dict[str, Any]:
    """The sim-to-real gap diagnosis of the task's recordings, written as ``usdeform diagnose`` writes it
    (diagnosis.json, record_next.json and report.html in the subject's folder)."""
    try:
        from ..gap import diagnose  # type: ignore[import-not-found,unused-ignore]
        from ..gap.report import write_report  # type: ignore[import-not-found,unused-ignore]
    except ImportError as error:
        raise UsdeformError(f"diagnosis: usdeform.gap is not available in this installation ({error})") from None
    diagnosis = diagnose([str(path) for path in task.recordings], seed=task.options.diagnosis_seed, progress=False)
    write_report(diagnosis, task.outputs[0].parent)
    return {"verdict": diagnosis.to_json().get("verdict")}


def task_record(
    task: TaskSpec, status: str, error: str | None, started: float, seconds: float | None, *, worker: str | None
) -> dict[str, Any]:
    """A record of ``task`` (see the module docstring) without inputs, outputs or details; ``started``
    in seconds since the epoch, ``worker`` the host:pid that ran it (None: it never ran)."""
    return {
        "id": task.id,
        "kind": task.kind,
        "subject": task.subject,
        "status": status,
        "error": error,
        "reused": False,
        "started": datetime.datetime.fromtimestamp(started, datetime.timezone.utc).isoformat(timespec="seconds"),
        "seconds": None if seconds is None else round(seconds, 3),
        "worker": worker,
        "inputs": [],
        "outputs": [],
        "options": task.option_values(),
        "details": {},
    }


def _here() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def one_line(error: BaseException) -> str:
    """``error`` as one line: its type and its message's first line."""
    message = str(error).strip().splitlines()
    return f"{type(error).__name__}: {message[0]}" if message else type(error).__name__


def run_task(task: TaskSpec, previous: dict[str, Any] | None = None, needed: dict[str, Any] | None = None) -> dict:
    """Run ``task`` here and return its record (see the module docstring).

    ``previous``: this task's record from the last run (None: none), reused if still valid.
    ``needed``: the record of the task it depends on (the fit, for a sweep); a sweep whose fit is not
    done is "skipped" with the reason.
    """
    started, clock = time.time(), time.perf_counter()
    if _still_valid(task, previous):
        assert previous is not None
        return {**previous, "reused": True}
    if task.depends_on is not None and (needed is None or needed.get("status") != "done"):
        reason = f"{needed['status']}: {needed['error']}" if needed else "not run"
        return task_record(task, "skipped", f"{task.depends_on} {reason}", started, 0.0, worker=_here())
    work: dict[TaskKind, Callable[[], dict[str, Any]]] = {
        "fit": lambda: stages.fit_position(
            task.recordings, task.options, task.outputs[0], task.outputs[1].parent if task.options.report else None
        ),
        "sweep": lambda: _reconstruct(task),
        "diagnosis": lambda: _diagnose(task),
    }
    for folder in {output.parent for output in task.outputs}:
        folder.mkdir(parents=True, exist_ok=True)
    _remove_partial_outputs(task)
    inputs = _fingerprints(task.inputs)  # before reading: a change during the run shows on the next one
    try:
        details = work[task.kind]()
    except _INPUT_FAILURES as error:
        return task_record(task, "failed", one_line(error), started, time.perf_counter() - clock, worker=_here())
    record = task_record(task, "done", None, started, time.perf_counter() - clock, worker=_here())
    outputs = _fingerprints(task.outputs)
    record.update(inputs=inputs or [], outputs=outputs or [], details=details)
    return record
