"""How many pixels the fused backend hands a worker at a time: whole `ev.reconstruct`
calls under block-size policies, alternating in one process.

Setup: one sweep of the ColorChecker at `--size` (default 360×1280), paper rig with
the `--sensor` preset (`realistic`: its noise model is then used, as after
calibration), the sensor's per-pixel thresholds, the fused backend on all usable
cores. Policies (`--policies`, default `512:512,2048:256`): `CAP:FLOOR` sets
`_fused.BLOCK_PIXELS` (the largest block) and `_fused.MIN_BLOCK_PIXELS` (the smallest);
`512:512` is the fixed 512-pixel block used before the twentieth session, `2048:256`
today's default (`_fused.block_pixels`: ~16 blocks per worker within those bounds).
One warm-up call, then `--repeats` rounds, each policy once per round; every cube is
checked equal to the warm-up's (the block size must not change an answer).

Printed and written: each policy's median and runs, the per-round ratio of each
policy's time to the first policy's (and its median: the least exposed to the
machine's drift), the load average and the same run's float32 matmul GFLOP/s.

    python experiments/bench_blocks.py [--size 360x1280] [--sensor ideal|realistic]
        [--repeats 5] [--policies 512:512,2048:256] [--out PATH]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax.random as jr
import numpy as np
from _common import matmul_gflops, write_json

import evhsi_jax as ev
from evhsi_jax._reconstruct import _fused


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="360x1280")
    ap.add_argument("--sensor", default="ideal", choices=["ideal", "realistic"])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--policies", default="512:512,2048:256")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    policies = [tuple(int(v) for v in p.split(":")) for p in args.policies.split(",")]
    h, w = ev.forward.parse_size(args.size)
    rig = ev.Rig(sensor=args.sensor)
    scene = ev.load_scene("colorchecker", (h, w))
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)
    maps = dict(threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off)

    def run():
        return ev.reconstruct(events, rig, backend="fused", **maps)

    first = np.asarray(run())
    saved = _fused.BLOCK_PIXELS, _fused.MIN_BLOCK_PIXELS
    times = {p: [] for p in policies}
    try:
        for _ in range(args.repeats):
            for p in policies:
                _fused.BLOCK_PIXELS, _fused.MIN_BLOCK_PIXELS = p
                t0 = time.perf_counter()
                cube = run()
                times[p].append(time.perf_counter() - t0)
                if not np.array_equal(np.asarray(cube), first):
                    raise SystemExit(f"policy {p}: the cube differs from the warm-up's")
    finally:
        _fused.BLOCK_PIXELS, _fused.MIN_BLOCK_PIXELS = saved
    gflops = matmul_gflops()
    base = policies[0]
    report = {"size": [h, w], "sensor": args.sensor, "pixels": h * w,
              "load": os.getloadavg()[0], "matmul_gflops": gflops, "policies": {}}  # fmt: skip
    for p in policies:
        ratios = [a / b for a, b in zip(times[base], times[p])]
        report["policies"][f"{p[0]}:{p[1]}"] = {
            "median_s": statistics.median(times[p]), "runs_s": times[p],
            "speedup_vs_first_per_round": ratios,
            "speedup_vs_first_median": statistics.median(ratios),
        }  # fmt: skip
        print(
            f"{args.size} {args.sensor}, blocks {p[0]}:{p[1]}: median "
            f"{statistics.median(times[p]):.2f} s (runs "
            f"{', '.join(f'{t:.2f}' for t in times[p])}); per-round speed-up over "
            f"{base[0]}:{base[1]} {statistics.median(ratios):.3f}x "
            f"({', '.join(f'{r:.2f}' for r in ratios)})"
        )
    print(f"float32 matmul {gflops:.0f} GFLOP/s, load {report['load']:.2f}")
    if args.out:
        write_json(args.out, report)


if __name__ == "__main__":
    main()
