"""Full-pipeline reconstruction speed (events → cube), float32, solver `auto`.

Setup: paper rig, one sweep of the ColorChecker (default 96×144), reconstructed with
the sensor's per-pixel thresholds (as after calibration). One warm-up call (compiles),
then `--repeats` timed calls; prints the median pixels/s, the individual times, the
load average, the float32 matmul GFLOP/s of the same run, the process's CPU time per
wall second and the metrics.

One XLA CPU device keeps only ~1.4 of 2 cores busy in this loop. With `--devices N` the
script asks XLA for N host devices (`XLA_FLAGS=--xla_force_host_platform_device_count=N`,
set before JAX starts) and shards the pixels over them (`mesh=ev.sharding.pixel_mesh(N)`), which
fills both cores.

Run: `.venv/bin/python experiments/bench_reconstruct.py [--size 96x144] [--repeats 5]
[--devices 2]` (under a minute).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--solver", default="auto")
    ap.add_argument("--devices", type=int, default=1)
    args = ap.parse_args()
    if args.devices > 1:  # must precede JAX's start
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "")
            + f" --xla_force_host_platform_device_count={args.devices}"
        )
    import jax.random as jr
    from _common import matmul_gflops  # after the device count is set

    import evhsi_jax as ev

    h, w = ev.forward.parse_size(args.size)
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", (h, w))
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)
    kw = dict(
        threshold_on_map=info.threshold_on,
        threshold_off_map=info.threshold_off,
        solver=args.solver,
    )
    if args.devices > 1:
        kw["mesh"] = ev.sharding.pixel_mesh(args.devices)
    ev.reconstruct(events, rig, **kw)
    times = []
    c0 = time.process_time()
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        cube = ev.reconstruct(events, rig, **kw)
        times.append(time.perf_counter() - t0)
    cpu = (time.process_time() - c0) / sum(times)
    med = statistics.median(times)
    print(
        f"{h}x{w} {args.solver} float32, {args.devices} device(s): median {med:.2f} s "
        f"-> {h * w / med:,.0f} px/s (runs {', '.join(f'{t:.2f}' for t in times)} s; "
        f"{cpu:.2f} CPU-s per s; load average {os.getloadavg()[0]:.2f}; float32 "
        f"matmul {matmul_gflops():.0f} GFLOP/s)"
    )
    print(ev.evaluate(cube, scene.truth_cube(rig.grid)))


if __name__ == "__main__":
    main()
