"""Cost of the noise-aware reconstruction against the ideal-sensor path.

Setup: paper rig, one sweep of the ColorChecker (default 48×72) from a sensor with
per-crossing threshold noise 0.01 (and, for the last row, a 10 kHz photoreceptor), the
true per-pixel thresholds; reconstructed (float32, solver `auto`) with

- "ideal path": a calibration whose sensor keys say ideal (every event exact);
- "noise path": threshold noise 0.01 and jitter 5 µs in the calibration (weighted rows,
  Huber reweighting where a sub-batch has an outlier, dim-channel prior);
- "noise + low-pass": as above plus `photoreceptor_hz` 10 000 (one Gauss–Newton pass of
  the linearised photoreceptor model: a second assembly and solve).

Each case on both backends (`--backends`): the fused CPU kernel on `--workers` threads
(default 1, to compare with the JAX path's one XLA device) and the JAX kernels. One
warm-up call each (compiles), then `--repeats` timed calls; medians in one process,
with the same run's float32 matmul GFLOP/s (1024² NumPy matmul) so that machines compare.

Run: `.venv/bin/python experiments/bench_noise_path.py [--size 48x72] [--repeats 5]`
→ experiments/results/bench_noise_path.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev


def matmul_gflops(n: int = 1024, repeats: int = 5) -> float:
    a = np.random.default_rng(0).standard_normal((n, n)).astype(np.float32)
    a @ a
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        a @ a
        times.append(time.perf_counter() - t)
    return 2 * n**3 / statistics.median(times) / 1e9


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="48x72")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="experiments/results/bench_noise_path.json")
    ap.add_argument("--backends", default="fused,jax")
    ap.add_argument(
        "--workers", type=int, default=1, help="threads of the fused backend (1)"
    )
    args = ap.parse_args()
    h, w = (int(v) for v in args.size.split("x"))
    scene = ev.load_scene("colorchecker", (h, w))
    sensor = ev.Rig(threshold_noise=0.01, photoreceptor_hz=10000.0)
    events, info = ev.simulate(scene, sensor, key=jr.key(3), return_info=True)
    truth = scene.truth_cube(sensor.grid)
    maps = (info.threshold_on, info.threshold_off)
    cases = {
        "ideal path": ev.Rig(),
        "noise path": ev.Rig(threshold_noise=0.01, timestamp_jitter_us=5.0),
        "noise + low-pass": ev.Rig(
            threshold_noise=0.01, timestamp_jitter_us=5.0, photoreceptor_hz=10000.0
        ),
    }
    rows = {}
    gflops = [matmul_gflops()]
    for backend in args.backends.split(","):
        for name, rig in cases.items():
            cal = ev.Calibration(rig, *maps)
            kw = dict(backend=backend, threads=args.workers)
            cube = ev.reconstruct(events, cal, **kw)  # warm-up: compiles
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                ev.reconstruct(events, cal, **kw)
                times.append(time.perf_counter() - t)
            med = statistics.median(times)
            m = ev.evaluate(cube, truth)
            rows[f"{name} ({backend})"] = {
                "backend": backend,
                "case": name,
                "median_s": med,
                "px_per_s": h * w / med,
                "times_s": times,
                "sam_deg": m["sam_deg"],
                "psnr_db": m["psnr_db"],
            }
            print(
                f"{name:18s} {backend:5s} {h * w / med:9,.0f} px/s  (median {med:.3f} "
                f"s)  SAM {m['sam_deg']:.2f}°  PSNR {m['psnr_db']:.2f} dB",
                flush=True,
            )
    gflops.append(matmul_gflops())
    for r in rows.values():
        base = rows[f"ideal path ({r['backend']})"]["median_s"]
        r["cost_vs_ideal"] = r["median_s"] / base
    print(
        "cost vs the same backend's ideal path: "
        + ", ".join(f"{k} {v['cost_vs_ideal']:.2f}x" for k, v in rows.items())
        + f"; float32 matmul {statistics.mean(gflops):.1f} GFLOP/s"
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"size": [h, w], "matmul_gflops": gflops, "rows": rows}, indent=2)
        + "\n"
    )


if __name__ == "__main__":
    main()
