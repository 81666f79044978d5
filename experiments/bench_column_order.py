"""What handing the fused kernel its pixels column by column saves on the
photoreceptor path.

With the photoreceptor rows, `_fused.solve_fused` solves the pixels column by column
(the band on a column's time grid is formed once per column) and moves the answers
back into the caller's order: three copies and a scatter of the (pixels × channels)
answers. `reconstruct` now hands it the pixels in column order already, so nothing
moves. Here both calls run alternately in one process on the same pixels, `realistic`
preset, the true rig as the calibration (`_kernel_setup.fused_inputs`), every usable
core: the pixels in flat order (answers moved back) and in column order (not moved).

Printed and written: each round's seconds, their medians, the median of the
per-round differences, whether the answers are the same bit for bit, the same run's
float32 matmul GFLOP/s.

    python experiments/bench_column_order.py [--size 360x640] [--repeats 3] [--out PATH]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from _common import matmul_gflops, write_json
from _kernel_setup import fused_inputs

from evhsi_jax._reconstruct import _fused


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="360x640")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="experiments/results/bench_column_order.json")
    args = ap.parse_args()
    s = fused_inputs("realistic", args.size)
    sel = s.sel
    by_col = s.prob.kernel_order(sel)  # (column by column: this preset's lowpass)
    sel_col = sel[by_col]
    _fused.solve_fused(s.prob, sel[:4096], *s.args)  # numba's compile or cache load
    times = {"flat order": [], "column order": []}
    for _ in range(args.repeats):
        t = time.perf_counter()
        xa, ka, _ = _fused.solve_fused(s.prob, sel, *s.args)
        times["flat order"].append(time.perf_counter() - t)
        t = time.perf_counter()
        xb, kb, _ = _fused.solve_fused(s.prob, sel_col, *s.args)
        times["column order"].append(time.perf_counter() - t)
    report = {
        "size": args.size,
        "pixels": int(sel.size),
        "times_s": times,
        "median_s": {k: statistics.median(v) for k, v in times.items()},
        "median_saved_s": statistics.median(
            a - b for a, b in zip(times["flat order"], times["column order"])
        ),
        "same_answers": bool(
            np.array_equal(xa[by_col], xb) and np.array_equal(ka[by_col], kb)
        ),
        "matmul_gflops_f32": matmul_gflops(),
    }
    print({k: v for k, v in report.items() if k != "times_s"}, flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
