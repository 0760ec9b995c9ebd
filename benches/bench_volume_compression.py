"""Write time and file size of a compounded volume at compression levels 1 (ISA-L), 2, 3, 6 and 9 (zlib) and
uncompressed, NRRD and MetaImage.

The volume: a simulated sweep of the coarse test phantom (``--frames`` frames of ``--size`` x ``--size``)
compounded at ``--spacing`` mm (float32, as ``usdeform correct`` and the batch write it), and the same
volume cast to uint8. Each write goes through :func:`usdeform.io.write_volume` to a fresh file; the
fastest of ``--repeats`` writes is reported (on a shared machine, the least disturbed one).

    python benches/bench_volume_compression.py [--size 256] [--frames 100] [--spacing 0.3]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from usdeform.io import write_volume
from usdeform.sim import coarse_phantom, simulate_sweep
from usdeform.volume import Volume, compound_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="frame rows = columns, pixels")
    parser.add_argument("--frames", type=int, default=100, help="frames of the sweep")
    parser.add_argument("--spacing", type=float, default=0.3, help="voxel size, mm")
    parser.add_argument("--repeats", type=int, default=5, help="writes per setting; the fastest is reported")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="usdeform-bench-compression-") as scratch:
        folder = Path(scratch)
        os.environ["USDEFORM_CACHE_DIR"] = str(folder / "cache")  # the phantom's solutions, solved afresh
        sweep, _ = simulate_sweep(
            coarse_phantom(), 10.0, 30.0, 8.0, n_frames=args.frames, seed=3, rows=args.size, cols=args.size
        )
        volume, _ = compound_recording(sweep, spacing_mm=args.spacing)
        volumes = {
            "float32": volume,
            "uint8": Volume(np.clip(np.rint(volume.image), 0, 255).astype(np.uint8), volume.grid),
        }
        print(
            f"volume: {args.frames}-frame {args.size} x {args.size} sweep compounded at {args.spacing} mm, "
            f"{' x '.join(map(str, volume.grid.shape))} voxels; fastest of {args.repeats} writes"
        )
        print("| voxels | format | level | seconds | MB |")
        print("|---|---|---|---|---|")
        for dtype, image_volume in volumes.items():
            for suffix in (".nrrd", ".mha"):
                for level in (1, 2, 3, 6, 9, None):
                    path = folder / f"volume{suffix}"
                    seconds = []
                    for _ in range(args.repeats):
                        path.unlink(missing_ok=True)
                        start = time.perf_counter()
                        write_volume(path, image_volume, compress=level is not None, compression_level=level or 1)
                        seconds.append(time.perf_counter() - start)
                    megabytes = path.stat().st_size / 1e6
                    name = "raw" if level is None else str(level)
                    print(f"| {dtype} | {suffix} | {name} | {min(seconds):.3f} | {megabytes:.2f} |")


if __name__ == "__main__":
    main()
