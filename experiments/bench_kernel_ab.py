"""The fused CPU kernel of an earlier revision against today's, in one process.

Whole-pipeline timings of two trees run in separate processes, and on a shared
machine whose speed drifts by tens of percent within an hour that hides a change of a
kernel. Here both kernels solve the same pixels in the same process, alternately:

Setup: one sweep of the ColorChecker at `--size` (default 96×144), paper rig with
the `--sensor` preset (`ideal`; `noise`: threshold noise 0.01 and 5 µs jitter, then
the noise-aware problem with its weights and reweighting; `realistic`: also the
photoreceptor rows), the true rig as the calibration, the true per-pixel thresholds;
the events screened and listed per pixel once (today's tree). Each kernel
(`_reconstruct/_fused_jit.py` of `--old`, taken with `git show`, and of the working
tree) solves all pixels on `--threads` threads: one warm-up call (numba compiles),
then `--repeats` rounds, each kernel once per round. The earlier kernel must take
the same arguments as today's `solve_pixels` (true since the kernel's `par`/`ipar`
layout of 2026-11). Each kernel gets the band table and spans its own tree computed
from the rig's table: trimmed at its `TRIM` (each band's entries above that fraction
of the band's peak, since the eighteenth session) or, for a kernel without one, the
table as it was with the spans of the rule before (above 1e-10 of the whole table's
peak).

Printed and written: µs per pixel (minimum and median of the rounds), the ratio of
the two kernels' times in each round and its median (each round runs both back to
back, so this ratio is the least exposed to the machine's drift), the largest
difference between the two answers and their SAM (largest, 99.9 %), the same run's
float32 matmul GFLOP/s.

    python experiments/bench_kernel_ab.py --old 1c1a37c [--sensor ideal|noise|realistic]
        [--size 96x144] [--repeats 5] [--threads 1] [--out PATH]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import matmul_gflops, source_at
from _kernel_setup import fused_inputs

from evhsi_jax._model import trim_rows
from evhsi_jax._reconstruct import _fused

KERNEL = "evhsi_jax/_reconstruct/_fused_jit.py"


def load_kernel(source: str, name: str, folder: Path):
    """The kernel module from its source text (its relative imports of the package
    made absolute), as a module of its own in a temporary folder (compiled afresh)."""
    text = source.replace("from ..", "from evhsi_jax.")
    path = folder / f"{name}.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    if "out_fit" not in mod.solve_pixels.py_func.__code__.co_varnames:
        # A kernel from before its per-pixel fit output (2026-11-29): called without it.
        old = mod.solve_pixels

        def without_fit(*a):
            return old(*a[:-1])

        without_fit.py_func = old.py_func
        mod.solve_pixels = without_fit
    return mod


def with_spans(prob, table, mod):
    """`prob` (a `FusedProblem`) with the band table, its sums and spans as kernel
    module `mod`'s tree made them from the rig's channel table `table` (float64; see
    the module docstring); a shallow copy."""
    import copy

    trim = getattr(mod, "TRIM", None)
    if trim is None:  # the rule before the eighteenth session
        tab = table
        big = np.abs(tab) > 1e-10 * np.abs(tab).max()
    else:
        tab = trim_rows(table, trim)
        big = tab != 0.0
    out = copy.copy(prob)
    out.table, out.tabsum = np.ascontiguousarray(tab), tab.sum(axis=1)
    out.span_lo, out.span_hi = _fused.row_spans(big)
    return out


def kernel_source(rev: str | None) -> str:
    """The kernel's source at git revision `rev` (None: the working tree)."""
    return source_at(rev, KERNEL)


def setup_args(doc: str, sensor: str) -> argparse.ArgumentParser:
    """The options of a kernel study: --sensor, --size, --out."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--sensor", default=sensor, choices=["ideal", "noise", "realistic"])
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--out", default=None)
    return ap


def main():
    ap = setup_args(__doc__, "realistic")
    ap.add_argument("--old", required=True, help="git revision of the earlier kernel")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    old_src, new_src = kernel_source(args.old), kernel_source(None)

    setup = fused_inputs(args.sensor, args.size)
    prob, sel, (h, w) = setup.prob, setup.sel, setup.size

    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        kernels = {
            "old": load_kernel(old_src, "kernel_old", Path(tmp)),
            "new": load_kernel(new_src, "kernel_new", Path(tmp)),
        }

        probs = {id(m): with_spans(prob, setup.table, m) for m in kernels.values()}

        def solve(mod):
            _fused_jit = sys.modules.get("evhsi_jax._reconstruct._fused_jit")
            sys.modules["evhsi_jax._reconstruct._fused_jit"] = mod
            import evhsi_jax._reconstruct as pkg

            saved, pkg._fused_jit = getattr(pkg, "_fused_jit", None), mod
            try:
                t = time.perf_counter()
                x, _, steps = _fused.solve_fused(
                    probs[id(mod)], sel, *setup.args, threads=args.threads
                )
                return time.perf_counter() - t, x, steps
            finally:
                sys.modules["evhsi_jax._reconstruct._fused_jit"] = _fused_jit
                pkg._fused_jit = saved

        answers = {k: solve(m)[1:] for k, m in kernels.items()}  # warm-up
        times = {k: [] for k in kernels}
        for _ in range(args.repeats):
            for k, m in kernels.items():
                times[k].append(solve(m)[0])
    gflops = matmul_gflops()
    xn, xo = answers["new"][0], answers["old"][0]
    dx = float(np.nanmax(np.abs(xn - xo)))
    cos = np.sum(xn * xo, 1) / np.maximum(
        np.linalg.norm(xn, axis=1) * np.linalg.norm(xo, axis=1), 1e-300
    )
    sam = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    sam_max, sam_999 = float(np.nanmax(sam)), float(np.nanquantile(sam, 0.999))
    rows = {}
    for k in kernels:
        us = [1e6 * t / sel.size for t in times[k]]
        rows[k] = {"us_per_px_min": min(us), "us_per_px_median": statistics.median(us),
                   "us_per_px": us}  # fmt: skip
        print(f"{k} ({args.old if k == 'old' else 'working tree'}): "
              f"{min(us):.1f} µs/px (median {statistics.median(us):.1f})")  # fmt: skip
    ratio = rows["old"]["us_per_px_median"] / rows["new"]["us_per_px_median"]
    # Each round times both kernels back to back: the per-round ratio is less
    # exposed to the machine's drift between rounds than the ratio of medians.
    per_round = [a / b for a, b in zip(times["old"], times["new"])]
    ratio_rounds = statistics.median(per_round)
    print(f"per-round old/new: median {ratio_rounds:.2f}x "
          f"({', '.join(f'{v:.2f}' for v in per_round)})")  # fmt: skip
    print(f"old/new {ratio:.2f}x; max |x_new - x_old| {dx:.2e}; SAM new to old: "
          f"max {sam_max:.1e}°, 99.9 % {sam_999:.1e}°; "
          f"{sel.size} pixels, {args.threads} thread(s), sensor {args.sensor}; "
          f"float32 matmul {gflops:.1f} GFLOP/s")  # fmt: skip
    if args.out:
        Path(args.out).write_text(json.dumps({
            "old": args.old, "sensor": args.sensor, "size": [h, w],
            "threads": args.threads, "pixels": int(sel.size), "rows": rows,
            "median_ratio_old_over_new": ratio,
            "per_round_ratio_old_over_new": per_round,
            "median_per_round_ratio": ratio_rounds, "max_abs_diff": dx,
            "sam_deg_max": sam_max, "sam_deg_999": sam_999,
            "matmul_gflops": gflops,
        }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
