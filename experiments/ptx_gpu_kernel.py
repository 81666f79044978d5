"""The GPU path's CUDA kernel compiled for a Hopper GPU on a machine without one: its
PTX, and from `ptxas -v` its registers, shared memory and spills, for each variant.
What a change does to the code (64-bit index arithmetic, local memory, register
pressure) shows here before any device time is spent; the time itself needs a GPU
(`bench_gpu_kernel.py`, `profile_gpu_kernel.py`).

Needs numba-cuda and CUDA's compiler libraries (NVVM, ptxas), all from PyPI — in a
virtual environment of its own, e.g.
`python -m venv /tmp/cu && /tmp/cu/bin/pip install numba 'numba-cuda[cu12]'` —
then `/tmp/cu/bin/python experiments/ptx_gpu_kernel.py [--variants shared:none,global:none]
[--cc 9.0] [--m 72] [--out DIR]`. The kernel module is imported by path, as in
`profile_gpu_kernel.py` (the package would import JAX). numba asks the current
device for its compute capability when it types a call of a device function; with
no device, the script answers `--cc` for it.

Prints, per variant: registers per thread, shared memory per block, spill bytes,
the PTX instruction count and how many of those are 64-bit integer operations
(`add.s64`, `mul.lo.s64`, ...). These are static counts over the whole kernel, not
executed instructions: most of the kernel runs rarely, and whether a hot loop is
lean shows in its own PTX (`--out`), its cost only in a profile (the first
kernel's profile found numba's 64-bit index arithmetic in its hot loops; README,
"One GPU"). On this machine, session of 2026-11-26, seventh: shared:none 79
registers, 25,120 bytes of shared memory; global:none 96 and 14,608; no spills.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from pathlib import Path


def _ptxas() -> str | None:
    """ptxas on the PATH, else the one of the nvidia-cuda-nvcc wheel."""
    found = shutil.which("ptxas")
    if found:
        return found
    try:
        import nvidia.cuda_nvcc as nvcc  # the wheel's package

        cand = Path(list(nvcc.__path__)[0]) / "bin" / "ptxas"
        return str(cand) if cand.exists() else None
    except ImportError:
        return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="shared:none,global:none")
    ap.add_argument("--cc", default="9.0", help="compute capability, e.g. 9.0")
    ap.add_argument("--m", type=int, default=72, help="channels (the paper rig: 72)")
    ap.add_argument("--out", default="", help="also write each variant's PTX here")
    args = ap.parse_args()
    try:
        from numba import cuda, types
        from numba.cuda import dispatcher
    except ImportError as err:
        print(f"error: needs numba-cuda ({err})", file=sys.stderr)
        return 2
    cc = tuple(int(v) for v in args.cc.split("."))

    class _Device:  # what numba asks the (absent) device for
        compute_capability = cc

    dispatcher.get_current_device = lambda: _Device()
    from profile_gpu_kernel import ck  # the kernel module alone, by path

    f32, i32 = types.float32, types.int32
    a3, a2, a1 = (types.Array(f32, n, "C") for n in (3, 2, 1))
    ai1 = types.Array(i32, 1, "C")
    # launch()'s argument types (the kernel's signature)
    sig = (a3, i32, a2, ai1, a3, a2, ai1, a1, f32, f32, f32, i32, a2, a2, a1, ai1)
    ptxas = _ptxas()
    print(f"cc {args.cc}, M = {args.m}, ptxas: {ptxas or 'not found'}")
    for var in filter(None, args.variants.split(",")):
        kw = ck.variant(var)
        kern = ck.make_kernel(
            args.m, ck.THREADS, kw["q_global"], kw["max_registers"], kw["prefetch"]
        )  # fmt: skip
        ptx, _ = cuda.compile_ptx(kern.py_func, sig, cc=cc)
        ops = re.findall(r"^\s+([a-z]+(?:\.[a-z0-9]+)*)", ptx, flags=re.M)
        ops = [o for o in ops if not o.startswith(".")]
        int64 = sum(
            bool(re.match(r"(add|sub|mul|mad|shl|shr|and|or|selp|setp\.\w+)\.[sub]64", o))
            for o in ops
        )  # fmt: skip
        line = f"{var}: {len(ops)} PTX instructions, {int64} on 64-bit integers"
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            (out / f"{var.replace(':', '_')}.ptx").write_text(ptx)
        if ptxas:
            with_ptx = Path(args.out or "/tmp") / f"_{var.replace(':', '_')}.ptx"
            with_ptx.write_text(ptx)
            res = subprocess.run(
                [ptxas, f"-arch=sm_{cc[0]}{cc[1]}", "-v", "-O3", str(with_ptx),
                 "-o", "/dev/null"],
                capture_output=True, text=True,
            )  # fmt: skip
            info = " ".join(
                m.group(0)
                for m in re.finditer(
                    r"Used \d+ registers|\d+ bytes smem|\d+ bytes spill stores",
                    res.stderr,
                )
            )  # fmt: skip
            line += f"; ptxas: {info or res.stderr.strip()[-200:]}"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
