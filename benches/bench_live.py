"""The live service end to end over loopback: ``replay`` -> ``live`` -> a viewer, 256 x 256 frames.

The service runs in its own process (as ``usdeform live`` does); this process replays a synthetic
sweep (``usdeform.live.synthetic``: 300 frames, 0.4 mm apart, looped with ever later timestamps, as a
robot sweeping the same 120 mm back and forth) at ``--rate`` frames per second and receives the
volumes as 3D Slicer would. Reported per run:

- latency to the volume: from the frame's IMAGE message read whole to its voxels in the compounder,
  the state the next volume sent is made of (the service's own clock); also after the first pass over
  the sweep, when the grid has stopped growing;
- delivered: from the replay sending the frame to the viewer holding a volume with it (both clocks
  are CLOCK_MONOTONIC of one machine), which adds the wait for the next volume (1 / volume rate) and
  its sending;
- frames dropped (sent but not corrected), volumes received per second, the service's resident memory
  (after the first 10 % of the run, at its end, and its largest).

    python benches/bench_live.py [--seconds 60] [--rate 30] [--volumes 2:float32 2:uint8 10:uint8] [--max-rate]
    python benches/bench_live.py --seconds 600 --volumes 2:float32          # the 10-minute memory run
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from usdeform.live import LiveClient, LiveServer, OutputSettings, replay
from usdeform.live.synthetic import synthetic_scan

VOLUME = OutputSettings().volume_name


def _scan(size: int, frames: int) -> Any:
    return synthetic_scan(frames, size, size, seed=1)


def _serve(size: int, frames: int, volume_rate: float, voxel_type: Any, ports: Any, results: Any) -> None:
    """The service's process: runs until it has had no message for 2 s, then reports."""
    model, sampled, _ = _scan(size, frames)
    server = LiveServer(
        model,
        sampled,
        listen=("127.0.0.1", 0),
        outputs=OutputSettings(volume_rate_hz=volume_rate),
        voxel_type=voxel_type,
        idle_stop_s=2.0,
        max_seconds=3600.0,
    ).start()
    ports.put((server.port, os.getpid()))
    result = server.run()
    results.put(
        {
            "latency_s": result.latency_s,
            "images_read": result.images_read,
            "frames_corrected": result.frames_corrected,
            "skipped": result.skipped,
            "volumes_sent": result.volumes_sent,
            "regrown": result.regrown,
        }
    )


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def run(size: int, frames: int, rate: float, seconds: float, volumes: str) -> dict[str, Any]:
    """One run (``volumes``: ``RATE:VOXEL_TYPE`` of the volumes sent); returns its numbers."""
    volume_rate, voxel_type = float(volumes.split(":")[0]), volumes.split(":")[1]
    context = multiprocessing.get_context("spawn")
    ports, results = context.Queue(), context.Queue()
    process = context.Process(target=_serve, args=(size, frames, volume_rate, voxel_type, ports, results))
    process.start()
    port, pid = ports.get(timeout=120)
    _, _, sweep = _scan(size, frames)
    client = LiveClient(("127.0.0.1", port), keep=100_000, max_seconds=seconds + 120)
    memory: list[tuple[float, float]] = []
    stop = threading.Event()

    def sample() -> None:
        start = time.perf_counter()
        while not stop.wait(1.0):
            memory.append((time.perf_counter() - start, _rss_mb(pid)))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    total = int(seconds * rate)
    loops = -(-total // len(sweep))
    sent = replay(sweep, ("127.0.0.1", port), rate_hz=rate, loops=loops, frames=total)
    stats = results.get(timeout=seconds + 600)
    process.join(timeout=60)
    stop.set()
    client.close()
    # Delivered latency: each frame from its sending to the first volume holding it.
    arrivals = [(t, int(m.metadata["FramesInserted"])) for t, m in client.messages if m.device_name == VOLUME]
    delivered, next_frame = [], 0
    for arrived, inserted in arrivals:
        while next_frame < min(inserted, len(sent.sent_at)):
            delivered.append(arrived - sent.sent_at[next_frame])
            next_frame += 1
    during = [t for t, _ in arrivals if t <= sent.sent_at[-1]]
    rss = [mb for t, mb in memory if t >= 0.1 * seconds]
    latency = np.array(stats["latency_s"]) * 1000
    steady = latency[len(sweep) :]  # after the first pass over the sweep: the grid has stopped growing
    delivered_ms = np.array(delivered) * 1000
    return {
        "rate": rate,
        "volumes": volumes,
        "sent": sent.frames_sent,
        "send_rate": sent.frames_sent / sent.seconds,
        "corrected": stats["frames_corrected"],
        "dropped": sent.frames_sent - stats["frames_corrected"],
        "skipped": stats["skipped"],
        "latency_ms": (np.median(latency), np.percentile(latency, 99), latency.max()),
        "steady_ms": (np.median(steady), np.percentile(steady, 99)) if steady.size else (np.nan,) * 2,
        "delivered_ms": (np.median(delivered_ms), np.percentile(delivered_ms, 99)) if delivered else (np.nan,) * 2,
        "volumes_per_s": (len(during) - 1) / (during[-1] - during[0]) if len(during) > 1 else float("nan"),
        "rss_mb": (rss[0], rss[-1], max(rss)) if rss else (np.nan,) * 3,
        "regrown": stats["regrown"],
    }


def _row(numbers: dict[str, Any]) -> str:
    latency, delivered, rss = numbers["latency_ms"], numbers["delivered_ms"], numbers["rss_mb"]
    steady = numbers["steady_ms"]
    return (
        f"| {numbers['rate']:g} ({numbers['send_rate']:.1f} sent) | {numbers['volumes']} | {numbers['sent']} | "
        f"{numbers['dropped']} | {latency[0]:.1f} / {latency[1]:.1f} / {latency[2]:.1f} | "
        f"{steady[0]:.1f} / {steady[1]:.1f} | "
        f"{delivered[0]:.1f} / {delivered[1]:.1f} | {numbers['volumes_per_s']:.1f} | "
        f"{rss[0]:.0f} / {rss[1]:.0f} / {rss[2]:.0f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="frame rows and columns")
    parser.add_argument("--frames", type=int, default=300, help="frames of the sweep replayed (looped)")
    parser.add_argument("--rate", type=float, default=30.0, help="frames per second")
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each run")
    parser.add_argument(
        "--volumes",
        nargs="+",
        default=["2:float32", "2:uint8", "10:uint8"],
        metavar="RATE:TYPE",
        help="volumes sent per second and their voxel type, one run each",
    )
    parser.add_argument(
        "--max-rate",
        action="store_true",
        help="also raise the rate by half until a 20 s run drops a frame, lags (median latency above 20 ms) or the "
        "replay cannot keep up",
    )
    args = parser.parse_args()
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the start")
    print(
        "| frames/s | volumes/s: voxel type | frames sent | dropped | latency to the volume, ms: median / p99 / max "
        "| the same after the first pass: median / p99 "
        "| delivered to the viewer, ms: median / p99 | volumes received /s | service RSS, MB: start / end / max |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for volumes in args.volumes:
        print(_row(run(args.size, args.frames, args.rate, args.seconds, volumes)), flush=True)
    if args.max_rate:
        rate = args.rate
        while True:
            rate *= 1.5
            numbers = run(args.size, args.frames, rate, 20.0, args.volumes[0])
            print(_row(numbers), flush=True)
            # Sustained: every frame corrected, no backlog (median latency within 20 ms), the replay kept up.
            if numbers["dropped"] or numbers["latency_ms"][0] > 20.0 or numbers["send_rate"] < 0.95 * rate:
                break
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
