"""``usdeform correct``: correct a sweep to zero force with a model file (and compound it)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ..compensation import add_compensation_options
from ..errors import InputError
from ..volume.command import add_volume_options

if TYPE_CHECKING:
    import numpy as np

__all__ = ["add_correct_command"]


def _correct(args: argparse.Namespace) -> None:
    from .._files import check_output_paths
    from ..io.sequence_file import SEQUENCE_SUFFIXES
    from ..io.volume_file import VOLUME_SUFFIXES
    from ..pipeline import PipelineSettings, correct_sweep

    if args.coverage is not None and args.volume is None:
        raise InputError("--coverage: needs --volume")
    check_output_paths(
        {
            "--output": (args.output, SEQUENCE_SUFFIXES),
            "--volume": (args.volume, VOLUME_SUFFIXES),
            "--coverage": (args.coverage, VOLUME_SUFFIXES),
        },
        {"SWEEP": args.sweep, "--model": args.model},
    )
    settings = PipelineSettings.from_arguments(args)
    run = correct_sweep(args.sweep, args.model, settings, args.output, args.volume, args.coverage)
    if run.compensation is not None:
        print(*run.compensation["notes"], sep="\n")
    force = run.recording.force
    assert force is not None  # checked by correct_sweep
    chosen = {
        "sweep": " (auto: every frame records ContactForce and ProbeDisplacement)",
        "interpolated": " (auto: the sweep does not record ProbeDisplacement)",
    }
    print(
        f"corrected {len(run.recording)} frames at {force.min():.2f}-{force.max():.2f} N with "
        f"stiffness from {len(run.sampled.profiles)} sampled positions"
        + (", rescaled to each frame's force and displacement" if run.stiffness_source == "sweep" else "")
        + f"; stiffness source {run.stiffness_source}"
        + (chosen[run.stiffness_source] if args.stiffness_source == "auto" else "")
        + f"; wrote {args.output}"
        + _mask_note(run.corrected.pixel_valid, args.output)
    )
    if run.volume is not None:
        print(
            f"compounded {run.n_compounded} corrected frames into {run.volume.grid.shape} voxels; wrote {args.volume}"
        )


def _mask_note(pixel_valid: np.ndarray | None, output: Path) -> str:
    """Where the corrected frames' pixels without data went (the companion file), or nothing."""
    from ..io import pixel_valid_path

    if pixel_valid is None or pixel_valid.all():
        return ""
    return (
        f" and its pixel validity mask ({100 * (1 - pixel_valid.mean()):.1f} % of the pixels hold no data) "
        f"to {pixel_valid_path(output)}"
    )


def add_correct_command(commands: argparse._SubParsersAction) -> None:
    """Register ``usdeform correct SWEEP --model MODEL --output FILE ...``."""
    correct = commands.add_parser("correct", help="correct a sweep to zero force with a model file")
    correct.add_argument(
        "sweep", type=Path, metavar="SWEEP", help="PLUS sequence file of the sweep, with ContactForce fields"
    )
    correct.add_argument(
        "--model", type=Path, required=True, metavar="MODEL", help="model file written by 'usdeform fit'"
    )
    correct.add_argument(
        "--output",
        type=Path,
        required=True,
        metavar="FILE",
        help="corrected sequence file (.seq.nrrd, .mha); pixels without data (sampled from outside "
        "the frame) go to a mask beside it, NAME.valid.seq.nrrd or NAME.valid.mha, named in its PixelValidFile field",
    )
    correct.add_argument(
        "--volume", type=Path, metavar="FILE", help="also compound the corrected frames into this volume file"
    )
    _add_correction_options(correct)
    add_compensation_options(correct)
    add_volume_options(correct, from_config=False)
    correct.set_defaults(run=_correct)


def _add_correction_options(correct: argparse.ArgumentParser) -> None:
    """The correction's settings, with the pipeline's defaults."""
    from ..pipeline import CHOICES, PipelineSettings

    defaults = PipelineSettings()
    correct.add_argument(
        "--stiffness-source",
        choices=CHOICES["stiffness_source"],
        default=defaults.stiffness_source,
        help="each frame's stiffness: interpolated between the palpated positions (the paper, eqs. 12-14), "
        "the interpolated profile rescaled to the frame's own ContactForce and ProbeDisplacement (sweep), or "
        "sweep where every frame records both, else interpolated (auto); the choice is printed and written to "
        f"the corrected file's StiffnessSource field (default: {defaults.stiffness_source})",
    )
    correct.add_argument(
        "--clamp-force",
        action="store_true",
        help="clamp ContactForce values outside the model's fitted range into it, with a warning "
        "(default: refuse them)",
    )
