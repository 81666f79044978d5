"""The reconstruction's host-side bookkeeping on a large sensor, stage by stage.

Setup: one sweep of the ColorChecker at `--size` (default 720×1280: ~25 M events),
paper rig, simulated once. Timed with the numba kernels, each the median of
`--repeats` runs in this process after one warm-up (numba compilation):

- `select_sweeps`: which sweeps a whole-file reconstruction uses;
- `screen_events`: the lit-interval screening and hot-pixel test;
- `pixel_lists`: every pixel's events in time order (the fused backend's input);
- `group_pixels`: the padded per-pixel batches of the JAX backend (CPU batch sizes).

The same script runs against an older tree (`PYTHONPATH=<tree> python
experiments/bench_host.py`) for a before/after on the same machine; the float32
matmul GFLOP/s of the same run is printed beside the times.

    python experiments/bench_host.py [--size 720x1280] [--repeats 3] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.random as jr
from _common import matmul_gflops, median_time

import evhsi_jax as ev
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct._pixels import group_pixels, pixel_lists


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    rig = ev.Rig()
    events = ev.simulate(ev.load_scene("colorchecker", (h, w)), rig, key=jr.key(0))
    t0 = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    period = float(pipe._rig_geometry(rig, w)["period_us"])
    screened = pipe.screen_events(events, rig, t0, None, 1, None)[0]
    chunk, sub = pipe.CPU_BATCH
    out = {"size": [h, w], "events": len(events), "source": ev.__file__}
    out["matmul_gflops"] = matmul_gflops()
    out["select_sweeps_s"] = median_time(
        lambda: pipe.select_sweeps(events.t_us, t0, period), args.repeats
    )
    out["screen_events_s"] = median_time(
        lambda: pipe.screen_events(events, rig, t0, None, 1, None), args.repeats
    )
    out["pixel_lists_s"] = median_time(
        lambda: pixel_lists(screened, t0), args.repeats
    )  # fmt: skip
    out["group_pixels_s"] = median_time(
        lambda: group_pixels(screened, t_start_us=t0, chunk_pixels=chunk,
                             min_chunk=sub, merge_below=chunk // 4),  # fmt: skip
        args.repeats,
    )
    print(json.dumps(out, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
