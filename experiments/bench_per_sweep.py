"""Per-sweep reconstruction of a recording (the video path): seconds per sweep, the
first sweep against the later ones, and each sweep's accuracy.

A recording's later sweeps differ from its first: each pixel's first event of a sweep
refers to the previous sweep's last one (the reference `reconstruct_sweeps` carries),
so that event's row spans the spectrum from blue to red. This study times it.

Setup: the paper rig, the ColorChecker at `--size` (default 720×1280), `--sweeps`
sweeps simulated in one capture (its per-pixel thresholds as the calibration), then
`ev.video.reconstruct_sweeps` of the in-memory events into a temporary folder,
`--repeats` times (each a fresh folder, the first after one untimed warm-up run of
one sweep). Printed and written: each sweep's reconstruction seconds (the index's
`seconds`: the `reconstruct` call, not the file's writing) per round, their medians
over rounds for the first sweep and for the later ones, the whole run's seconds per
sweep (cutting the events into sweeps, reconstructing, rendering and writing each
sweep's file), each sweep's SAM / PSNR
against the truth, the float32 matmul GFLOP/s of the same run. Compare two trees by
running it with `PYTHONPATH` on each.

    python experiments/bench_per_sweep.py [--size 720x1280] [--sweeps 3]
        [--repeats 2] [--out results/bench_per_sweep.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import jax.random as jr
import numpy as np
from _common import OUT, matmul_gflops

import evhsi_jax as ev


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--sweeps", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=OUT / "bench_per_sweep.json")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", (h, w))
    t0 = time.perf_counter()
    events, info = ev.simulate(
        scene, rig, sweeps=args.sweeps, key=jr.key(0), return_info=True
    )  # fmt: skip
    print(f"simulated {len(events):,} events in {time.perf_counter() - t0:.1f} s")
    truth = scene.truth_cube(rig.grid)
    maps = dict(
        threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
    )
    rounds, walls, quality = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        ev.video.reconstruct_sweeps(
            events, rig, Path(tmp) / "warm", max_sweeps=1, preview=False, **maps
        )  # fmt: skip
        for r in range(args.repeats):
            out = Path(tmp) / f"run{r}"
            res = ev.video.reconstruct_sweeps(events, rig, out, preview=False, **maps)
            rounds.append([e["seconds"] for e in res.index["sweeps"]])
            walls.append(res.seconds / len(rounds[-1]))
            print(f"round {r}: " + ", ".join(f"{s:.2f}" for s in rounds[-1])
                  + f" s; whole run {walls[-1]:.2f} s per sweep")  # fmt: skip
            if r == 0:
                for _, cube in ev.video.iter_sweep_cubes(out):
                    quality.append(ev.metrics.evaluate(np.asarray(cube["cube"]), truth))
    first = statistics.median(r[0] for r in rounds)
    later = statistics.median(s for r in rounds for s in r[1:])
    res = {
        "size": [h, w], "sweeps": args.sweeps, "events": len(events),
        "seconds_per_round": rounds, "first_sweep_median_s": first,
        "later_sweeps_median_s": later,
        "whole_run_s_per_sweep": walls,
        "sam_deg": [round(float(q["sam_deg"]), 4) for q in quality],
        "psnr_db": [round(float(q["psnr_db"]), 3) for q in quality],
        "matmul_gflops": matmul_gflops(),
    }  # fmt: skip
    print(
        f"first sweep {first:.2f} s, later sweeps {later:.2f} s (medians), whole run "
        f"{statistics.median(walls):.2f} s per sweep (reading, cutting, writing); SAM° "
        + " / ".join(f"{v:.3f}" for v in res["sam_deg"])
        + f"; float32 matmul {res['matmul_gflops']:.0f} GFLOP/s"
    )
    args.out.write_text(json.dumps(res, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
