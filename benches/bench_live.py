"""The live service end to end over loopback: ``replay`` -> ``live`` -> a separate viewer, 256 x 256 frames.

Three processes, as a lab runs them: the service (as ``usdeform live``), the viewer (as 3D Slicer's
OpenIGTLinkIF connector) and this one, which replays a synthetic sweep (``usdeform.live.synthetic``: 300
frames, 0.4 mm apart, looped with ever later timestamps, as a robot sweeping the same 120 mm back and forth)
at ``--rate`` frames per second. Reported per run:

- frame latency at the viewer: from the replay sending a frame to the viewer holding its corrected frame
  (``CorrectedImage``; both clocks are CLOCK_MONOTONIC of one machine): median, p99 and max; the largest gap
  between two corrected frames received, and the largest stall the service and the viewer added: a gap
  between two frames received less the gap between their sending (the replay, starved of a core, also
  leaves gaps);
- the viewer's own longest garbage collection (a pause of its reading: the viewer keeps the times it
  measures, not the messages, so that its collections stay short however long the run);
- frames dropped (sent but not corrected, or corrected but not received);
- the service's own latency per frame: from the IMAGE message read whole to the corrected frame queued
  for the viewers and compounded;
- volumes received per second;
- the machine's 1-minute load average during the run (mean and max of one sample a second): on 2
  cores, anything above 2 means processes wait for a core, and the latency's tail with them;
- the service's resident memory (RSS, sampled every second) during the scan: when the first pass over
  the sweep ended (the grid has stopped growing), half-way between that and the last frame sent, and
  at the last frame; the growth over that time (least-squares slope, MB per minute); and its peak
  while finishing (the final volume compounded from the stored frames, the recording written).

``--soak``: the same with a second viewer that connects and never reads (its receive buffer 1 KiB), and a
stray sender in the middle of the run: one IMAGE stamped with the wall clock (pyigtl's default) and one
ProbeToReference from another connection.

Before the runs, the CRC-64 OpenIGTLink needs of each volume sent, over ``--crc-mb`` MB: pyigtl's
(crcmod, holding the interpreter lock) against the Rust core's (``usdeform.live.transport.crc64``,
without it), each with the longest time another Python thread (ticking every 0.5 ms) waited meanwhile.

    python benches/bench_live.py [--seconds 60] [--rate 30] [--volumes 2:float32 2:uint8] [--max-rate]
    python benches/bench_live.py --seconds 180 --volumes 2:float32 --soak      # slow viewer, stray sender
"""

from __future__ import annotations

import argparse
import gc
import multiprocessing
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from usdeform.live import LiveClient, LiveServer, OutputSettings, replay
from usdeform.live.synthetic import synthetic_scan
from usdeform.live.transport import crc64, pyigtl_module

VOLUME, FRAME = OutputSettings().volume_name, OutputSettings().frame_name


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


def _memory(memory: list[tuple[float, float]], sent_at: list[float], first_pass: int) -> tuple[float, ...]:
    """Service RSS, MB: when the replay's first pass over the sweep ended (``sent_at[first_pass]``, the
    grid has stopped growing), at half the replay and at its last frame; the growth between the first
    and the last of these, MB per minute (least-squares slope); the peak after the last frame
    (finishing). NaN where no sample fell."""
    times, rss = np.array([t for t, _ in memory]), np.array([mb for _, mb in memory])
    first, last = sent_at[min(first_pass, len(sent_at) - 1)], sent_at[-1]

    def at(time_s: float) -> float:
        before = rss[times <= time_s]
        return float(before[-1]) if before.size else float("nan")

    scan = (times >= first) & (times <= last)
    slope = np.polyfit(times[scan], rss[scan], 1)[0] * 60 if scan.sum() >= 2 else float("nan")
    finishing = rss[(times > last) & np.isfinite(rss)]  # NaN once the service has exited
    peak = float(finishing.max()) if finishing.size else float("nan")
    return at(first), at((first + last) / 2), at(last), slope, peak


def crc_stalls(megabytes: float, repeats: int = 5) -> list[tuple[str, float, float]]:
    """For each CRC-64 of OpenIGTLink (pyigtl's, the Rust core's), the median time of one volume of
    ``megabytes`` MB and the longest wait of another Python thread (ticking every 0.5 ms) during those
    runs, ms; first the same wait with no CRC running for as long (the machine's own scheduling delay)."""
    data = np.random.default_rng(0).integers(0, 256, int(megabytes * 2**20), dtype=np.uint8)
    view = data.data.cast("B")
    implementations = [("pyigtl (crcmod)", pyigtl_module().messages.CRC64), ("Rust core", crc64)]
    assert implementations[0][1](view) == implementations[1][1](view)
    start = time.perf_counter()
    implementations[0][1](view)
    pyigtl_s = time.perf_counter() - start
    rows = []
    for name, crc in [("none (a sleep as long as pyigtl's)", lambda _: time.sleep(pyigtl_s)), *implementations]:
        stop, gaps = threading.Event(), [0.0]

        def tick(stop: threading.Event = stop, gaps: list[float] = gaps) -> None:
            last = time.perf_counter()
            while not stop.is_set():
                time.sleep(0.0005)
                now = time.perf_counter()
                gaps[0], last = max(gaps[0], now - last), now

        ticker = threading.Thread(target=tick)
        ticker.start()
        time.sleep(0.05)
        durations = []
        for _ in range(repeats):
            start = time.perf_counter()
            crc(view)
            durations.append(time.perf_counter() - start)
        stop.set()
        ticker.join()
        rows.append((name, 1000 * float(np.median(durations)), 1000 * gaps[0]))
    return rows


def _view(port: int, seconds: float, arrivals: Any) -> None:
    """The viewer's process: (timestamp, arrival) of every corrected frame, the volume arrivals, and the
    longest pause of its own garbage collector, s. It keeps the times only, not the messages: holding
    every message (70,000 in 10 minutes) made its full collections pause its reading for up to 0.2 s."""
    pauses, started = [0.0], [0.0]

    def collecting(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
        else:
            pauses[0] = max(pauses[0], time.perf_counter() - started[0])

    gc.callbacks.append(collecting)
    client = LiveClient(("127.0.0.1", port), keep=16, keep_pixels=False, max_seconds=seconds, timing=True)
    arrivals.put("connected")
    client._thread.join()
    client.close()
    frames = list(zip(client.timestamps.get(FRAME, []), client.arrivals.get(FRAME, []), strict=True))
    arrivals.put((frames, list(client.arrivals.get(VOLUME, [])), pauses[0]))


def _stray(port: int) -> None:
    """Another sender: one IMAGE stamped with the wall clock and one ProbeToReference, then it closes."""
    pyigtl = pyigtl_module()
    with socket.create_connection(("127.0.0.1", port)) as stray:
        image = pyigtl.ImageMessage(np.zeros((1, 256, 256), np.uint8), device_name="Image_Reference")
        stray.sendall(image.pack() + pyigtl.TransformMessage(np.eye(4), device_name="ProbeToReference").pack())
        time.sleep(0.5)


def _sent_timestamps(sweep: Any, total: int) -> np.ndarray:
    """The timestamps replay gives its first ``total`` frames (each loop's after the last one's)."""
    times = sweep.timestamps
    period = float(times[-1] - times[0]) + max(float(np.median(np.diff(times))), 1e-3)
    count = np.arange(total)
    return times[count % len(times)] + (count // len(times)) * period


def run(size: int, frames: int, rate: float, seconds: float, volumes: str, soak: bool = False) -> dict[str, Any]:
    """One run (``volumes``: ``RATE:VOXEL_TYPE`` of the volumes sent); returns its numbers."""
    volume_rate, voxel_type = float(volumes.split(":")[0]), volumes.split(":")[1]
    context = multiprocessing.get_context("spawn")
    ports, results, arrivals = context.Queue(), context.Queue(), context.Queue()
    process = context.Process(target=_serve, args=(size, frames, volume_rate, voxel_type, ports, results))
    process.start()
    port, pid = ports.get(timeout=120)
    _, _, sweep = _scan(size, frames)
    viewer = context.Process(target=_view, args=(port, seconds + 60, arrivals))
    viewer.start()
    slow = None
    if soak:
        slow = socket.socket()
        slow.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
        slow.connect(("127.0.0.1", port))
    assert arrivals.get(timeout=120) == "connected"
    time.sleep(0.5)  # the service has accepted it
    memory: list[tuple[float, float]] = []  # (time.perf_counter(), service RSS MB)
    load: list[float] = []  # the machine's 1-minute load average, each second
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(1.0):
            memory.append((time.perf_counter(), _rss_mb(pid)))
            load.append(os.getloadavg()[0])

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    total = int(seconds * rate)
    if soak:
        threading.Timer(seconds / 2, _stray, args=(port,)).start()
    loops = -(-total // len(sweep))
    sent = replay(sweep, ("127.0.0.1", port), rate_hz=rate, loops=loops, frames=total, clock="recording")
    stats = results.get(timeout=seconds + 600)
    process.join(timeout=60)
    stop.set()
    received, volume_arrivals, viewer_gc_s = arrivals.get(timeout=seconds + 120)
    viewer.join(timeout=60)
    if slow is not None:
        slow.close()
    # Each corrected frame received, matched to its sending by timestamp.
    stamps = _sent_timestamps(sweep, sent.frames_sent)
    latency_ms, arrived, sent_of = [], [], []
    for timestamp, arrival in received:
        index = int(np.argmin(np.abs(stamps - timestamp)))
        latency_ms.append(1000 * (arrival - sent.sent_at[index]))
        arrived.append(arrival)
        sent_of.append(sent.sent_at[index])
    latency = np.array(latency_ms)
    first_pass = sent.sent_at[min(len(sweep), len(sent.sent_at) - 1)]
    steady = np.array([ms for ms, arrival in zip(latency_ms, arrived, strict=True) if arrival > first_pass + 1.0])
    order = np.argsort(arrived)
    gaps = np.diff(np.array(arrived)[order]) * 1000 if len(arrived) > 1 else np.array([np.nan])
    added = gaps - np.diff(np.array(sent_of)[order]) * 1000 if len(arrived) > 1 else gaps
    service = np.array(stats["latency_s"]) * 1000
    during = [t for t in volume_arrivals if t <= sent.sent_at[-1]]
    return {
        "rate": rate,
        "volumes": volumes,
        "sent": sent.frames_sent,
        "send_rate": sent.frames_sent / sent.seconds,
        "corrected": stats["frames_corrected"],
        "dropped": sent.frames_sent - stats["frames_corrected"],
        "not_received": sent.frames_sent - len(received),
        "skipped": stats["skipped"],
        "frame_ms": (np.median(latency), np.percentile(latency, 99), latency.max()) if latency.size else (np.nan,) * 3,
        "steady_ms": (np.median(steady), np.percentile(steady, 99), steady.max()) if steady.size else (np.nan,) * 3,
        "gap_ms": float(np.max(gaps)),
        "stall_ms": float(np.max(added)),
        "service_ms": (np.median(service), np.percentile(service, 99)),
        "volumes_per_s": (len(during) - 1) / (during[-1] - during[0]) if len(during) > 1 else float("nan"),
        "rss_mb": _memory(memory, sent.sent_at, len(sweep)),
        "regrown": stats["regrown"],
        "load": (float(np.mean(load)), float(np.max(load))) if load else (np.nan, np.nan),
        "viewer_gc_ms": 1000 * viewer_gc_s,
    }


def _row(numbers: dict[str, Any]) -> str:
    frame, service, rss = numbers["frame_ms"], numbers["service_ms"], numbers["rss_mb"]
    steady = numbers["steady_ms"]
    return (
        f"| {numbers['rate']:g} ({numbers['send_rate']:.1f} sent) | {numbers['volumes']} | {numbers['sent']} | "
        f"{numbers['dropped']} / {numbers['not_received']} | {frame[0]:.1f} / {frame[1]:.1f} / {frame[2]:.1f} | "
        f"{steady[0]:.1f} / {steady[1]:.1f} / {steady[2]:.1f} | "
        f"{numbers['gap_ms']:.0f} / {numbers['stall_ms']:.0f} | {numbers['viewer_gc_ms']:.1f} | "
        f"{service[0]:.1f} / {service[1]:.1f} | {numbers['volumes_per_s']:.1f} | "
        f"{rss[0]:.0f} / {rss[1]:.0f} / {rss[2]:.0f} ({rss[3]:+.2f} MB/min) | {rss[4]:.0f} | "
        f"{sum(numbers['skipped'].values())} | {numbers['load'][0]:.1f} / {numbers['load'][1]:.1f} |"
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
        default=["2:float32", "2:uint8"],
        metavar="RATE:TYPE",
        help="volumes sent per second and their voxel type, one run each",
    )
    parser.add_argument(
        "--max-rate",
        action="store_true",
        help="also raise the rate by half until a 20 s run drops a frame, lags (median latency above 20 ms) or the "
        "replay cannot keep up",
    )
    parser.add_argument("--soak", action="store_true", help="with a viewer that never reads and a stray sender")
    parser.add_argument(
        "--crc-mb",
        type=float,
        default=6.0,
        help="bytes of the volume whose CRC is timed, MB (the sweep's volumes sent: about 83 x 240 x 75 float32)",
    )
    args = parser.parse_args()
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the start")
    rows = crc_stalls(args.crc_mb)
    print(f"| CRC-64 of {args.crc_mb:g} MB | ms per volume (median of 5) | longest wait of another thread, ms |")
    print("|---|---|---|")
    for name, duration, stall in rows:
        print(f"| {name} | {duration:.1f} | {stall:.1f} |")
    print(
        f"Rust / pyigtl: {rows[2][1] / rows[1][1]:.2f} x the time, "
        f"{rows[2][2] / rows[1][2]:.2f} x the longest wait of another thread"
    )
    print(
        "| frames/s | volumes/s: voxel type | frames sent | dropped: not corrected / not received "
        "| frame latency at the viewer, ms: median / p99 / max | the same after the first pass "
        "| largest gap between frames received / less the gap between their sending, ms "
        "| the viewer's longest garbage collection, ms "
        "| service latency, ms: median / p99 | volumes received /s "
        "| service RSS after the first pass, MB: start / middle / end (growth) | service RSS peak while finishing, MB "
        "| images skipped | load average during the run: mean / max |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for volumes in args.volumes:
        print(_row(run(args.size, args.frames, args.rate, args.seconds, volumes, soak=args.soak)), flush=True)
    if args.max_rate:
        rate = args.rate
        while True:
            rate *= 1.5
            numbers = run(args.size, args.frames, rate, 20.0, args.volumes[0])
            print(_row(numbers), flush=True)
            # Sustained: every frame corrected, no backlog (median latency within 20 ms), the replay kept up.
            if numbers["dropped"] or numbers["frame_ms"][0] > 20.0 or numbers["send_rate"] < 0.95 * rate:
                break
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
