"""Four lanes or eight: the fused kernel's lane factorisation and solve
(`_fused_jit._solve_lanes`, float64 × 4) against the same code written out for eight
pixels (float64 × 8, one AVX-512 register), on systems the kernel itself assembled.

Setup: one sweep of the ColorChecker at `--size` (default 96×144), paper rig with
the `--sensor` preset (as `bench_kernel_ab.py`); every `--stride`-th pixel with
events, at most `--pixels`, run through the kernel's Python source around its
compiled inner functions, and each four-lane system handed to `_solve_lanes` copied
(Q, q and the union envelope, as `kernel_envelope.py` reads them). Two consecutive
four-lane groups make one eight-lane group: lanes 0–3 and 4–7, the envelope the
smaller of the two first columns per row (the entries outside a pixel's own envelope
are exact zeros, so each pixel's answer is its four-lane answer up to the grouping of
the sums).

The eight-lane functions are generated from a template that mirrors `_lane_factor`
and `_lane_solve` line for line (two partial sums per dot product in the
factorisation, four in the forward substitution), compiled with the kernel's
`njit(slp=True, error_model="numpy")`. Each group is solved `--inner` times in a row
(its Q stays in the cache, as in the kernel, where the solve follows the assembly);
the two widths alternate for `--repeats` rounds. Printed and written: µs per pixel
(minimum over rounds), the median per-round ratio, the factorisation's multiply-adds per
pixel over either union envelope, the largest difference of the answers, the float32 matmul GFLOP/s.

    python experiments/bench_lane_width.py [--sensor ideal] [--size 96x144]
        [--pixels 1600] [--stride 7] [--inner 20] [--repeats 7] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
from _common import OUT, matmul_gflops
from _kernel_setup import fused_inputs, run_lane_solves
from bench_kernel_ab import kernel_source, load_kernel

from evhsi_jax._base import njit


def captured_systems(sensor: str, size: str, stride: int, pixels: int):
    """The four-lane systems (Q, q, envelope) the kernel solves for a sample of the
    capture's pixels, and M."""
    setup = fused_inputs(sensor, size)
    sel = np.ascontiguousarray(setup.sel[::stride][:pixels], np.int64)
    caps = []
    with tempfile.TemporaryDirectory() as tmp:
        sys.path.insert(0, tmp)
        kernel = load_kernel(kernel_source(None), "kernel_lane_width", Path(tmp))
        run_lane_solves(
            kernel, setup, sel,
            lambda ql, qvl, fu: caps.append((ql.copy(), qvl.copy(), fu.copy())),
        )  # fmt: skip
    m = setup.prob.channels
    ql, qv, fu = (np.stack([c[i] for c in caps]) for i in range(3))
    return kernel, ql, qv, fu, m


def lane_source(n: int) -> str:
    """`solve_lanes{n}`: `_solve_lanes` written out for `n` lanes (entry (i, j) of
    lane l at n (i M + j) + l). The template's lines are code; a line `@ FMT` is
    repeated for each lane with `{l}` the lane and `{h}` the lane + n, and `@0
    NAMES` zeroes the accumulators NAMES of every lane."""
    template = """
def factor{n}(ql, ptr, fu, lf, inv, fail, m):
    for i in range(m):
        fi = fu[i]
        pi = ptr[i] - fi
        e = U({n} * (pi + i))
        @ d{l} = ql[e + U({l})]
        for j in range(fi, i):
            pj = ptr[j] - fu[j]
            e = U({n} * (pi + j))
            @ s{l} = ql[e + U({l})]
            k0 = max(fi, fu[j])
            n2 = (j - k0) // 2
            @0 t
            for q in range(U(n2)):
                k = U(k0) + U(2) * q
                a = U({n}) * (U(pi) + k)
                b = U({n}) * (U(pj) + k)
                @ s{l} -= lf[a + U({l})] * lf[b + U({l})]
                @ t{l} -= lf[a + U({h})] * lf[b + U({h})]
            if k0 + 2 * n2 < j:
                a = U({n} * (pi + j - 1))
                b = U({n} * (pj + j - 1))
                @ s{l} -= lf[a + U({l})] * lf[b + U({l})]
            @ s{l} += t{l}
            c = U({n} * j)
            @ v{l} = s{l} * inv[c + U({l})]
            @ lf[e + U({l})] = v{l}
            @ d{l} -= v{l} * v{l}
        c = U({n} * i)
        @ inv[c + U({l})] = pivot(d{l}, fail, {l})


def lsolve{n}(lf, ptr, fu, inv, qv, out, m):
    for i in range(m):
        pi = ptr[i] - fu[i]
        @0 abce
        k0 = fu[i]
        n4 = (i - k0) // 4
        for q in range(U(n4)):
            k = U(k0) + U(4) * q
            a = U({n}) * (U(pi) + k)
            o = U({n}) * k
            @ a{l} += lf[a + U({l})] * out[o + U({l})]
            @ b{l} += lf[a + U({l} + {n})] * out[o + U({l} + {n})]
            @ c{l} += lf[a + U({l} + 2 * {n})] * out[o + U({l} + 2 * {n})]
            @ e{l} += lf[a + U({l} + 3 * {n})] * out[o + U({l} + 3 * {n})]
        for k in range(U(k0 + 4 * n4), U(i)):
            a = U({n}) * (U(pi) + k)
            o = U({n}) * k
            @ a{l} += lf[a + U({l})] * out[o + U({l})]
        c = U({n} * i)
        @ out[c + U({l})] = (-qv[c + U({l})] - ((a{l} + b{l}) + (c{l} + e{l}))) * inv[c + U({l})]
    for i in range(m - 1, -1, -1):
        c = U({n} * i)
        @ x{l} = out[c + U({l})] * inv[c + U({l})]
        @ out[c + U({l})] = x{l}
        pi = ptr[i] - fu[i]
        for k in range(U(fu[i]), U(i)):
            d = U({n}) * k
            sk = U({n}) * (U(pi) + k)
            @ w{l} = out[d + U({l})]
            @ out[d + U({l})] = w{l} - x{l} * lf[sk + U({l})]


def solve_lanes{n}(ql, qvl, fu, ptr, lf, inv, xl, fail, m):
    for i in range(m):
        ptr[i] = i * m + fu[i]
    for lane in range({n}):
        fail[lane] = False
    factor{n}(ql, ptr, fu, lf, inv, fail, m)
    lsolve{n}(lf, ptr, fu, inv, qvl, xl, m)
"""
    out = []
    for line in template.splitlines():
        body = line.lstrip()
        pad = line[: len(line) - len(body)]
        if body.startswith("@0 "):
            names = [f"{g}{lane}" for g in body[3:] for lane in range(n)]
            out.append(pad + " = ".join(names) + " = 0.0")
        elif body.startswith("@ "):
            out += [pad + body[2:].format(l=lane, h=lane + n, n=n) for lane in range(n)]
        else:
            out.append(line.replace("{n}", str(n)))
    return "\n".join(out) + "\n"


def compile_lanes(n: int, kernel):
    """The generated `solve_lanes{n}`, compiled as the kernel's lane functions."""
    jit = njit(slp=True, error_model="numpy")
    ns = {"U": kernel._u, "pivot": kernel._lane_pivot, "math": math}
    exec(compile(lane_source(n), f"<lanes{n}>", "exec"), ns)  # noqa: S102
    for name in (f"factor{n}", f"lsolve{n}", f"solve_lanes{n}"):
        ns[name] = jit(ns[name])
    return ns[f"solve_lanes{n}"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sensor", default="ideal")
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--pixels", type=int, default=1600)
    ap.add_argument("--stride", type=int, default=7)
    ap.add_argument("--inner", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", type=Path, default=OUT / "bench_lane_width.json")
    args = ap.parse_args()
    kernel, ql4, qv4, fu4, m = captured_systems(
        args.sensor, args.size, args.stride, args.pixels
    )
    n = ql4.shape[0] // 2 * 2
    ql4, qv4, fu4 = ql4[:n], qv4[:n], fu4[:n]
    g8 = n // 2
    ql8 = np.zeros((g8, m * m, 8))
    ql8[..., :4] = ql4[0::2].reshape(g8, m * m, 4)
    ql8[..., 4:] = ql4[1::2].reshape(g8, m * m, 4)
    qv8 = np.zeros((g8, m, 8))
    qv8[..., :4] = qv4[0::2].reshape(g8, m, 4)
    qv8[..., 4:] = qv4[1::2].reshape(g8, m, 4)
    ql8, qv8 = ql8.reshape(g8, -1), qv8.reshape(g8, -1)
    fu8 = np.minimum(fu4[0::2], fu4[1::2])

    solve4, solve8 = kernel._solve_lanes, compile_lanes(8, kernel)

    def runner(solve, lanes):
        @numba.njit  # not cached: it closes over the solve it times
        def run(ql, qv, fu, m, inner):
            ptr = np.zeros(m, np.int64)
            lf = np.zeros(lanes * m * m)
            inv = np.zeros(lanes * m)
            xl = np.zeros((ql.shape[0], lanes * m))
            fail = np.zeros(lanes, np.bool_)
            for g in range(ql.shape[0]):
                for _ in range(inner):
                    solve(ql[g], qv[g], fu[g], ptr, lf, inv, xl[g], fail, m)
            return xl

        return run

    run4, run8 = runner(solve4, 4), runner(solve8, 8)
    x4 = run4(ql4, qv4, fu4, m, 1).reshape(g8, 2, m, 4)
    x8 = run8(ql8, qv8, fu8, m, 1).reshape(g8, m, 8)
    diff = max(
        float(np.abs(x8[..., :4] - x4[:, 0]).max()),
        float(np.abs(x8[..., 4:] - x4[:, 1]).max()),
    ) / float(np.abs(x4).max())

    def madds(fu):  # per lane, so per pixel: each lane works over the union
        w = np.arange(m) - fu
        return float((w * (w + 1) / 2).sum(1).mean())

    t4, t8 = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        run4(ql4, qv4, fu4, m, args.inner)
        t4.append(time.perf_counter() - t)
        t = time.perf_counter()
        run8(ql8, qv8, fu8, m, args.inner)
        t8.append(time.perf_counter() - t)
    px = n * 4 * args.inner
    res = {
        "sensor": args.sensor, "size": args.size, "lane_systems": int(n),
        "channels": int(m),
        "us_per_px_4": min(t4) / px * 1e6, "us_per_px_8": min(t8) / px * 1e6,
        "ratio_per_round_median": statistics.median(a / b for a, b in zip(t4, t8)),
        "factor_madds_per_px_4": madds(fu4), "factor_madds_per_px_8": madds(fu8),
        "max_rel_diff": diff, "matmul_gflops": matmul_gflops(),
    }  # fmt: skip
    print(
        f"{n} four-lane systems ({args.sensor}, {args.size}): 4 lanes "
        f"{res['us_per_px_4']:.2f} µs/px, 8 lanes {res['us_per_px_8']:.2f} µs/px, "
        f"8 lanes {res['ratio_per_round_median']:.2f}× as fast (per-round median); "
        f"factorisation multiply-adds per pixel {res['factor_madds_per_px_4']:.0f} → "
        f"{res['factor_madds_per_px_8']:.0f}; answers within {diff:.1e}; float32 "
        f"matmul {res['matmul_gflops']:.0f} GFLOP/s"
    )
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
