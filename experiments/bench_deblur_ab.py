"""The deblurring (`_reconstruct/_deblur.py`) of an earlier revision against today's,
in one process.

Setup: a random float32 cube of `--size` × 73 channels in [0, 1) (seed 0; the
deblurring's cost does not depend on the values), the `realistic` preset's PSF
(σ = 0.5 px). Each version (`deblur_cube` of `--old`, taken with `git show`, and of
the working tree) runs once per round, alternately, for `--repeats` rounds after one
warm-up call each, on every usable core (SciPy's FFT workers).

Printed and written: the seconds of each round, their medians, the median of the
per-round ratios, the largest difference between the two answers, each version's
peak of allocated memory during one call (`tracemalloc`, which sees NumPy's
buffers; beside the input cube), the same run's float32 matmul GFLOP/s.

    python experiments/bench_deblur_ab.py --old 20ed699 [--size 720x1280]
        [--repeats 5] [--out PATH]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from _common import matmul_gflops, source_at, write_json

from evhsi_jax._reconstruct import _deblur as new
from evhsi_jax.forward import parse_size


def _old_module(rev: str):
    """`_deblur` at revision `rev`, loaded as a module of the package (its relative
    imports resolve) under another name."""
    src = source_at(rev, "evhsi_jax/_reconstruct/_deblur.py")
    path = Path(tempfile.mkdtemp()) / "old_deblur.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(
        "evhsi_jax._reconstruct._old_deblur", path
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", required=True)
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="experiments/results/bench_deblur_ab.json")
    args = ap.parse_args()
    old = _old_module(args.old)
    h, w = parse_size(args.size)
    cube = np.random.default_rng(0).random((h, w, 73), dtype=np.float32)
    sigma = 0.5
    a = old.deblur_cube(cube, sigma)
    b = new.deblur_cube(cube, sigma)
    peak_mb = {}
    for key, mod in (("old", old), ("new", new)):
        tracemalloc.start()
        mod.deblur_cube(cube, sigma)
        peak_mb[key] = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
    times = {"old": [], "new": []}
    for _ in range(args.repeats):
        for key, mod in (("old", old), ("new", new)):
            t = time.perf_counter()
            mod.deblur_cube(cube, sigma)
            times[key].append(time.perf_counter() - t)
    report = {
        "old": args.old,
        "size": [h, w, 73],
        "times_s": times,
        "median_s": {k: statistics.median(v) for k, v in times.items()},
        "ratio_old_over_new_median": statistics.median(
            o / n for o, n in zip(times["old"], times["new"])
        ),
        "max_abs_diff": float(np.abs(a - b).max()),
        "peak_mb": peak_mb,
        "matmul_gflops_f32": matmul_gflops(),
    }
    print({k: v for k, v in report.items() if k != "times_s"}, flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
