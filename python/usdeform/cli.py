"""The ``usdeform`` command line.

usdeform demo [--output DIR] [--quick]      the whole method on the simulator, with report.html
usdeform reconstruct SEQUENCE --output FILE  compound a PLUS sequence file into a volume
usdeform fit PALPATION... --output MODEL     fit a deformation model to palpations, write a model file
usdeform correct SWEEP --model MODEL --output FILE [--volume FILE]
                                             correct a sweep to zero force (and compound it)
usdeform simulate palpation|sweep --output DIR [--effect NAME:P=V,...]
                                             simulated recordings with their ground truth
usdeform experiment paper-2d --output DIR    reproduce the paper's 2D experiments on the simulator
usdeform experiment paper-3d --output DIR    reproduce the paper's 3D experiments on the simulator
usdeform experiment clinical-3d --output DIR correct clinical-shaped sweeps (artery and vein) per vessel
usdeform batch MANIFEST --out DIR [--scheduler ADDRESS] [--workers N]
                                             fit, correct and reconstruct a cohort on a Dask cluster
usdeform diagnose RECORDING... --out DIR     diagnose the gap between recordings and the simulator
usdeform gap-benchmark --cases N --out DIR   score the diagnosis on cases with a withheld effect
usdeform compensation-benchmark --cases N --out DIR
                                             what an effect costs the corrected volume, what --compensate recovers
usdeform live --model MODEL --listen HOST:PORT
                                             correct and compound a scan live from OpenIGTLink, send it to 3D Slicer
usdeform replay RECORDING --to HOST:PORT     play a sequence file over OpenIGTLink as PLUS Server would
"""

from __future__ import annotations

# Only light imports here: every command imports what it needs when it runs, inside main()'s handlers,
# so that Ctrl-C at any moment of a run is "usdeform: interrupted" and "usdeform --help" imports no
# command's dependencies (SciPy's statistics, Matplotlib, Dask, OpenCV, the simulator).
import argparse
import importlib
import shlex
import signal
import sys
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from .errors import UsdeformError

__all__ = ["build_parser", "main"]


#: The commands in the order of ``usdeform --help``: (module and function that registers the command; the
#: one-line help of the command's placeholder).
_COMMANDS: dict[str, tuple[tuple[str, str], str]] = {
    "demo": ((".demo.command", "add_demo_command"), "the whole method on the simulator, with report.html"),
    "simulate": ((".sim.command", "add_simulate_command"), "simulate palpations or sweeps with their ground truth"),
    "reconstruct": ((".volume.command", "add_reconstruct_command"), "compound a PLUS sequence file into a volume"),
    "fit": (
        (".fitting.command", "add_fit_command"),
        "fit a deformation model to palpations, write a model file (JSON)",
    ),
    "correct": ((".correction.command", "add_correct_command"), "correct a sweep to zero force with a model file"),
    "experiment": (
        (".experiments.command", "add_experiment_command"),
        "reproduce the paper's experiments on the simulator",
    ),
    "batch": ((".batch.command", "add_batch_command"), "fit, correct and reconstruct a cohort on a Dask cluster"),
    "diagnose": ((".gap.command", "add_diagnose_command"), "diagnose the sim-to-real gap of palpation recordings"),
    "gap-benchmark": ((".gap.command", "add_gap_benchmark_command"), "score the gap diagnosis on withheld effects"),
    "compensation-benchmark": (
        (".compensation_benchmark.command", "add_compensation_benchmark_command"),
        "what a recording effect costs the corrected volume and what --compensate gives back",
    ),
    "import-bag": ((".io.command", "add_import_bag_command"), "convert a ROS1/ROS2 bag into a PLUS sequence file"),
    "live": ((".live.command", "add_live_command"), "correct and compound a scan live from OpenIGTLink"),
    "replay": ((".live.command", "add_replay_command"), "play a sequence file over OpenIGTLink as PLUS Server would"),
}


def _chosen_command(argv: list[str] | None) -> str:
    """The command named in ``argv`` (its first argument that is not an option), or "" if none."""
    return next((part for part in (sys.argv[1:] if argv is None else argv) if not part.startswith("-")), "")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``usdeform`` parser; each command sets ``run``, the function that executes it.

    ``command``: only that command's parser is built in full (and only its modules imported); the others
    are placeholders with their help, enough for ``usdeform --help``. None: every command in full."""
    parser = argparse.ArgumentParser(prog="usdeform", description="Deformation-aware robotic 3D ultrasound.")
    commands = parser.add_subparsers(dest="command", required=True)
    for name, ((module, function), help_text) in _COMMANDS.items():
        if command is not None and name != command:
            commands.add_parser(name, help=help_text)
        else:
            getattr(importlib.import_module(module, __package__), function)(commands)
    return parser


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that temporary files are removed on the way out."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise _Terminated


@contextmanager
def _terminate_cleanly() -> Iterator[None]:
    """SIGTERM raises :class:`_Terminated` (from the main thread; kernels notice it every 64 frames)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _show_warning(message: Warning | str, category: type[Warning], *args: Any, **kwargs: Any) -> None:
    print(f"usdeform: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (None: ``sys.argv``); returns the exit status: 0, 2 on errors,
    130 on Ctrl-C and 143 on SIGTERM (both leave no partial output).

    The handlers are in place before anything else: building the parser imports the chosen command's
    modules, which takes a second or two, and Ctrl-C then must not print a traceback."""
    try:
        with _terminate_cleanly(), warnings.catch_warnings():
            from .validation import ForceClampWarning  # NumPy: imported where Ctrl-C is handled

            args = build_parser(_chosen_command(argv)).parse_args(argv)
            args.command_line = "usdeform " + shlex.join(sys.argv[1:] if argv is None else argv)
            warnings.simplefilter("always", ForceClampWarning)
            warnings.showwarning = _show_warning
            args.run(args)
    except (UsdeformError, OSError) as error:
        print(f"usdeform: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("usdeform: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print("usdeform: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    return 0


if __name__ == "__main__":
    sys.exit(main())
