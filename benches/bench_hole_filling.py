"""Benchmark of the hole filling: the Rust kernel against its NumPy twin on the real SpinePhantom volume.

The real PLUS sweep SpinePhantomFreehand.igs.mha (public data kept outside the repository) is
compounded with the configuration PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml (LINEAR,
MEAN) onto the grid of PLUS's SpinePhantomFreehandReconstructed.mha (147 x 106 x 104 voxels of
0.5 mm), then filled with the configuration's STICK step and with a 5^3 GAUSSIAN step. Prints the median time of each.

    python benches/bench_hole_filling.py [--plus-data FOLDER]

The PLUS data folder is ``--plus-data``, else ``$USDEFORM_SHARED_DATA/plus``, else ``../shared/data/plus``
beside the clone (as the tests' ``plus_data`` fixture).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # spinning BLAS workers would take a core

from functools import partial
from pathlib import Path

import numpy as np

from bench_kernels import median_seconds
from usdeform import reference
from usdeform.io import read_plus_config, read_sequence, read_volume
from usdeform.volume import PLUS_MIN_KNOWN_WEIGHT, Compounder, HoleFillingElement, fill_holes

SHARED_DATA = Path(os.environ.get("USDEFORM_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plus-data", type=Path, default=SHARED_DATA / "plus", help="the PLUS data folder")
    data = parser.parse_args().plus_data
    if not data.is_dir():
        parser.error(f"{data}: no PLUS data folder (it is not part of the repository); give --plus-data")
    config = read_plus_config(data / "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml")
    settings = config.reconstruction
    assert settings is not None
    recording = read_sequence(data / "SpinePhantomFreehand.igs.mha", config=config)
    grid = read_volume(data / "SpinePhantomFreehandReconstructed.mha").grid
    compounder = Compounder(grid, settings.interpolation, settings.compounding)
    compounder.add_frames(recording.frames[recording.pose_valid], recording.image_to_base[recording.pose_valid])
    volume = compounder.volume()
    weight = volume.weight
    assert weight is not None
    holes = int((weight < PLUS_MIN_KNOWN_WEIGHT).sum())
    print(f"volume {grid.shape} (z, y, x), {holes} holes of {volume.image.size} voxels")
    steps = {
        "STICK (configured)": list(settings.hole_filling),
        "GAUSSIAN 5^3": [HoleFillingElement("gaussian", size=5, stdev=1.0, min_known_ratio=0.0)],
    }
    print("| step | rust, all cores (s) | rust, 1 thread (s) | numpy twin (s) | numpy / rust all cores |")
    print("|---|---|---|---|---|")
    for name, elements in steps.items():
        rust = median_seconds(partial(fill_holes, volume, elements), 5)
        rust_one = median_seconds(partial(fill_holes, volume, elements, threads=1), 3)
        twin = median_seconds(partial(reference.fill_holes, volume.image, weight, elements, PLUS_MIN_KNOWN_WEIGHT), 1)
        same = np.allclose(
            fill_holes(volume, elements).image,
            reference.fill_holes(volume.image, weight, elements, PLUS_MIN_KNOWN_WEIGHT),
            rtol=1e-6,
            atol=1e-4,
        )
        assert same, f"{name}: the kernel and its NumPy twin disagree"
        print(f"| {name} | {rust:.3f} | {rust_one:.3f} | {twin:.2f} | {twin / rust:.1f}x |")


if __name__ == "__main__":
    main()
