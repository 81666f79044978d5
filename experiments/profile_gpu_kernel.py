"""The GPU path's CUDA kernel under a profiler, in a process without JAX: Nsight Compute
(`ncu`) crashed attached to the JAX process of `bench_gpu_kernel.py` (H100, JAX
0.11.2, session of 2026-11-26, seventh), so the rows of one chunk are saved there
(`bench_gpu_kernel.py --save-rows rows.npz`) and solved here, each kernel variant
once warm and once between `cuda.profile_start()` and `cuda.profile_stop()`:

    python experiments/bench_gpu_kernel.py --save-rows /tmp/rows.npz ...
    EVHSI_CUDA_LINEINFO=1 ncu --profile-from-start off --set full -o kern \\
        python experiments/profile_gpu_kernel.py /tmp/rows.npz \\
        [--variants shared:none,shared:none:pf]

Variants as `bench_gpu_kernel.py --variants` (PLACE:REGS[:pf|nopf]); the default
kernel is launched first. Also prints each launch's time (wall clock around the
synchronised call, median of `--repeats` outside the profiled range) and whether its
answers equal the default's.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

# The kernel module alone (the package would import JAX).
KERNEL = Path(__file__).parents[1] / "evhsi_jax" / "_reconstruct" / "_cuda_kernel.py"


def load_kernel(path=KERNEL, name="_cuda_kernel"):
    """A revision of the kernel module (this tree's by default), imported by path."""
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ck = load_kernel()


def main():
    from numba import cuda

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rows", help="an .npz of bench_gpu_kernel.py --save-rows")
    ap.add_argument("--variants", default="shared:none")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--compare", default="", metavar="PY",
        help="also time the default kernel of another version of _cuda_kernel.py "
        "(`git show REV:evhsi_jax/_reconstruct/_cuda_kernel.py > old.py`)",
    )  # fmt: skip
    args = ap.parse_args()
    z = np.load(args.rows)
    rows = SimpleNamespace(
        events=cuda.to_device(z["events"]), drift=cuda.to_device(z["drift"]),
        spec_weight=cuda.to_device(z["spec_weight"]),
    )  # fmt: skip
    counts = cuda.to_device(z["counts"].astype(np.int32))
    prior = z["prior"]
    ridge, tol, iters = float(z["ridge"]), float(z["tol"]), int(z["iters"])
    print("pixels", z["events"].shape, "drift", z["drift"].shape, flush=True)
    variants = {"default": {}}
    variants.update({v: ck.variant(v) for v in args.variants.split(",") if v})

    if args.compare:
        variants["compare"] = {"module": load_kernel(args.compare, "_other_kernel")}

    def run(kw):
        kw = dict(kw)
        mod = kw.pop("module", ck)
        return mod.solve_rows(rows, counts, prior, ridge, tol, iters, **kw)

    answers = {}
    for name, kw in variants.items():  # compile, warm, time outside the profile
        out = run(kw)[0]
        answers[name] = out.copy_to_host() if hasattr(out, "copy_to_host") else out
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            run(kw)  # (returns after the kernel finished)
            times.append(time.perf_counter() - t)
        same = np.array_equal(answers[name], answers["default"], equal_nan=True)
        print(
            f"{name}: {statistics.median(times) * 1e3:.2f} ms "
            f"({z['events'].shape[0] / statistics.median(times) / 1e6:.2f} M px/s), "
            f"same answers as default: {same}, "
            f"{ck.resources(prior.shape[0], **kw) if 'module' not in kw else ''}",
            flush=True,
        )  # fmt: skip
    cuda.synchronize()
    if ck.simulated():  # (no profiler there: the script's own check)
        return
    cuda.profile_start()
    for kw in variants.values():
        run(kw)
    cuda.synchronize()
    cuda.profile_stop()
    print("profiled", list(variants), flush=True)


if __name__ == "__main__":
    sys.exit(main())
