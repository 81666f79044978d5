"""Full-pipeline reconstruction speed (events → cube), solver `auto`, per backend.

Setup: paper rig, ideal sensor (`--sensor realistic`: the `realistic` preset, whose
noise model — threshold noise, jitter, 10 kHz photoreceptor — the reconstruction then
uses, as after calibrating a real rig; `--sensor threshold-noise`: per-crossing
threshold noise 0.01 alone; `--sensor background`: background activity of 1 Hz per
pixel alone, whose stray events inside the lit intervals `reconstruct` searches for
and removes unless `--stray-z 0`), one sweep (`--sweeps N`: N) of the ColorChecker (default
96×144), reconstructed with the sensor's per-pixel thresholds (as after calibration). Per
backend one warm-up call (compiles), then `--repeats` timed calls, all in one process;
prints and stores the warm-up call's time (compilation included, unless the
caches hold it), the median pixels/s, the individual times, the process's CPU time
per wall second, the metrics against the truth, the load average and the float32
matmul GFLOP/s of the same run (so runs on different machines compare).

Backends (`--backends`, default both): `fused` — the CPU kernel of
`evhsi_jax/_reconstruct/_fused.py` on `--workers` threads; `jax` — the compiled JAX
chunk kernels, float32, on `--workers` XLA host devices (`XLA_FLAGS=
--xla_force_host_platform_device_count=N`, set before JAX starts, pixels sharded with
`ev.sharding.pixel_mesh(N)`; one device keeps only ~1.4 of 2 cores busy).

`--reference`: also solve the same events with the JAX path in float64 (slow: a few
thousand px/s) and report, per backend, the share of pixels within 0.1° SAM of it —
the issue's "equal accuracy" test.

Run: `.venv/bin/python experiments/bench_reconstruct.py [--size 96x144] [--repeats 5]
[--workers 2] [--sensor ideal|realistic|threshold-noise|background] [--sweeps 1]
[--stray-z Z] [--sweep-speed auto|off] [--lowpass-scan auto|sequential|associative]
[--reference]
[--out experiments/results/bench_reconstruct.json]`.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--backends", default="fused,jax")
    ap.add_argument(
        "--workers", type=int, default=None, help="threads / XLA devices (all cores)"
    )
    ap.add_argument("--reference", action="store_true")
    ap.add_argument(
        "--sensor",
        default="ideal",
        choices=["ideal", "realistic", "threshold-noise", "background"],
    )
    ap.add_argument(
        "--stray-z",
        type=float,
        default=None,
        help="ProblemConfig.stray_z (default its default; 0: no search for strays)",
    )
    ap.add_argument(
        "--sweeps", type=int, default=1, help="sweeps of the static recording (1)"
    )
    ap.add_argument(
        "--sweep-speed",
        default="auto",
        choices=["auto", "off"],
        help="reconstruct's sweep_speed (auto: each sweep's mirror speed measured "
        "from the recording; off: the rig's)",
    )
    ap.add_argument(
        "--lowpass-scan",
        default="auto",
        choices=["auto", "sequential", "associative"],
        help="the JAX path's photoreceptor filter recursion (_problem.LOWPASS_SCAN; "
        "auto: sequential on a CPU)",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    workers = args.workers or len(os.sched_getaffinity(0))
    if workers > 1:  # must precede JAX's start
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "")
            + f" --xla_force_host_platform_device_count={workers}"
        )
    import jax
    import jax.random as jr
    import numpy as np
    from _common import matmul_gflops  # after the device count is set

    import evhsi_jax as ev
    from evhsi_jax._reconstruct import _problem

    _problem.LOWPASS_SCAN = args.lowpass_scan
    h, w = ev.forward.parse_size(args.size)
    if args.sensor == "threshold-noise":
        rig = ev.Rig.from_dict({"threshold_noise": 0.01})
    elif args.sensor == "background":
        rig = ev.Rig.from_dict({"noise_rate_hz": 1.0})
    else:
        rig = ev.Rig(sensor=args.sensor)
    scene = ev.load_scene("colorchecker", (h, w))
    t0 = time.perf_counter()
    events, info = ev.simulate(
        scene, rig, sweeps=args.sweeps, key=jr.key(0), return_info=True
    )
    print(f"simulated {len(events):,} events in {time.perf_counter() - t0:.1f} s")
    truth = scene.truth_cube(rig.grid)
    maps = dict(
        threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
    )
    if args.stray_z is not None:
        maps["config"] = ev.reconstruction.ProblemConfig(stray_z=args.stray_z)
    maps["sweep_speed"] = args.sweep_speed
    ref = None
    if args.reference:
        t0 = time.perf_counter()
        with jax.enable_x64(True):
            ref = ev.reconstruct(events, rig.astype(np.float64), backend="jax", **maps)
        print(f"float64 JAX reference in {time.perf_counter() - t0:.1f} s")
    results = {
        "size": [h, w],
        "sensor": args.sensor,
        "sweeps": args.sweeps,
        "stray_z": args.stray_z,
        "sweep_speed": args.sweep_speed,
        "lowpass_scan": args.lowpass_scan,
        "events": len(events),
        "workers": workers,
        "backends": {},
    }
    for backend in args.backends.split(","):
        kw = dict(maps, backend=backend)
        if backend == "fused":
            kw["threads"] = workers
        elif workers > 1:
            kw["mesh"] = ev.sharding.pixel_mesh(workers)
        t0 = time.perf_counter()
        ev.reconstruct(events, rig, **kw)  # warm-up: compilation
        first = time.perf_counter() - t0
        times = []
        c0 = time.process_time()
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            cube = ev.reconstruct(events, rig, **kw)
            times.append(time.perf_counter() - t0)
        cpu = (time.process_time() - c0) / sum(times)
        med = statistics.median(times)
        gflops = matmul_gflops()
        metrics = ev.evaluate(cube, truth)
        row = {
            "first_call_s": first,  # compilation (or the caches' loading) included
            "median_s": med,
            "px_per_s": h * w / med,
            "runs_s": times,
            "cpu_s_per_s": cpu,
            "load": os.getloadavg()[0],
            "matmul_gflops": gflops,
            "sam_deg": metrics["sam_deg"],
            "psnr_db": metrics["psnr_db"],
        }
        if ref is not None:
            s = ev.metrics.sam_map_deg(cube, ref)
            row["within_0.1deg_of_float64"] = float(np.mean(s <= 0.1))
            row["sam_to_float64_max_deg"] = float(s.max())
        results["backends"][backend] = row
        extra = (
            f"; {100 * row['within_0.1deg_of_float64']:.3f} % within 0.1° of float64 "
            f"(max {row['sam_to_float64_max_deg']:.3f}°)"
            if ref is not None
            else ""
        )
        print(
            f"{h}x{w} {backend}, {workers} worker(s): first call {first:.1f} s; "
            f"median {med:.2f} s -> "
            f"{h * w / med:,.0f} px/s (runs {', '.join(f'{t:.2f}' for t in times)} s; "
            f"{cpu:.2f} CPU-s per s; load {row['load']:.2f}; float32 matmul "
            f"{gflops:.0f} GFLOP/s); SAM {metrics['sam_deg']:.3f}°, PSNR "
            f"{metrics['psnr_db']:.2f} dB{extra}"
        )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(args.out).with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.replace(args.out)


if __name__ == "__main__":
    main()
