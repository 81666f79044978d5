"""Width of the lane factorisation's envelope and its multiply-adds, per group of four
pixels, for today's fused kernel and optionally an earlier revision's.

The envelope (the first column in use in each row of Q, the smallest over the group's
four pixels) sets the factorisation's work: Σ_i w_i (w_i + 1) / 2 multiply-adds for
row widths w_i. It is read where the kernel hands Q to the lane solve
(`_solve_lanes`), by running the kernel's Python source (`py_func`) for the group
steps around compiled inner functions: slow, hence a sample of pixels.

Setup: one sweep of the ColorChecker at `--size` (default 96×144), paper rig with the
`--sensor` preset (as `bench_kernel_ab.py`), every `--stride`-th pixel with events, at
most `--pixels` of them.

    python experiments/kernel_envelope.py [--old 397cbe3] [--sensor ideal]
        [--pixels 80] [--stride 97] [--out PATH]
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from _kernel_setup import fused_inputs, run_lane_solves
from bench_kernel_ab import kernel_source, load_kernel, setup_args


def envelope(mod, setup, sel):
    """Mean row width of the envelope and mean multiply-adds of the factorisation per
    lane solve, over the solves of the pixels `sel`."""
    widths = []
    run_lane_solves(
        mod, setup, sel, lambda ql, qvl, fu: widths.append(np.arange(fu.size) - fu)
    )  # fmt: skip
    w = np.array(widths)
    return {"solves": len(w), "mean_width": float(w.mean()),
            "max_width": int(w.max()),
            "factor_madds": float((w * (w + 1) / 2).sum(1).mean())}  # fmt: skip


def main():
    ap = setup_args(__doc__, "ideal")
    ap.add_argument("--old", default=None, help="git revision to compare with")
    ap.add_argument("--pixels", type=int, default=80)
    ap.add_argument("--stride", type=int, default=97)
    args = ap.parse_args()
    setup = fused_inputs(args.sensor, args.size)
    sel = np.ascontiguousarray(setup.sel[:: args.stride][: args.pixels], np.int64)
    sources = {"new": kernel_source(None)}
    if args.old:
        sources["old"] = kernel_source(args.old)
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        for k, src in sources.items():
            res[k] = envelope(
                load_kernel(src, f"kernel_env_{k}", Path(tmp)), setup, sel
            )
            print(f"{k} ({args.old if k == 'old' else 'working tree'}): "
                  f"{res[k]['solves']} lane solves, envelope {res[k]['mean_width']:.1f} "
                  f"columns per row (max {res[k]['max_width']}), "
                  f"{res[k]['factor_madds']:.0f} multiply-adds per factorisation")  # fmt: skip
    if args.out:
        Path(args.out).write_text(json.dumps(
            {"sensor": args.sensor, "size": args.size, "pixels": int(sel.size),
             "old": args.old, **res}, indent=2,
        ))  # fmt: skip


if __name__ == "__main__":
    main()
