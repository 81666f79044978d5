"""Where the JAX solve's time goes on a device: batched Cholesky and triangular solves
of the reconstruction's size (a diagnosis for the GPU path, `experiments/bench_gpu.py`).

Setup: `--batch` random symmetric positive definite `m × m` float32 systems (m = 73,
the paper rig's channels; Q = AᵀA/m + I with A standard normal, fresh per run), on
JAX's default device, full float32 matrix products. Timed (median of `--repeats` warm
runs, each on its own inputs drawn before the clock starts):

- `cho_factor`: `jax.scipy.linalg.cho_factor` alone;
- `cho_solve`: `jax.scipy.linalg.cho_solve` alone (two batched triangular solves);
- `substitution`: the same two triangular solves as `m` row steps each of batched
  dot products (`substitution_solve` below; measured no faster on an H100, so the
  package keeps the library's solve);
- `unconstrained`: factor + solve as the reconstruction calls it
  (`_solvers.unconstrained`), and the same with the substitution solve;
- `gram`: QᵀQ-like products of the same size (a batched matmul, for scale).

Each variant's answer is checked against float64 NumPy on 64 of the systems
(relative error printed). Prints one JSON object; `--out` writes it.

    python experiments/bench_gpu_linalg.py [--batch 131072] [--m 73] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from _common import matmul_gflops

from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct import _solvers


def substitution_solve(c, b):
    """$(LL^T)^{-1} b$ from the lower Cholesky factor `c` (its upper triangle is
    ignored) by forward and back substitution, one row per step (`lax.fori_loop`):
    under `vmap` each step is a batched dot product — the same answer as
    `cho_solve`, written without a triangular-solve library call (the alternative
    timed here; checked against float64 NumPy below)."""
    m = b.shape[0]
    low = jnp.tril(c)
    up = low.T  # rows of Lᵀ, contiguous

    def fwd(i, y):
        return y.at[i].set((b[i] - low[i] @ y) / low[i, i])

    def bwd(j, x):
        i = m - 1 - j
        return x.at[i].set((y[i] - up[i] @ x) / low[i, i])

    y = jax.lax.fori_loop(0, m, fwd, jnp.zeros_like(b))
    return jax.lax.fori_loop(0, m, bwd, jnp.zeros_like(b))


def systems(key, batch, m):
    a = jr.normal(key, (batch, m, m), jnp.float32)
    q = jnp.einsum("bki,bkj->bij", a, a) / m + jnp.eye(m, dtype=jnp.float32)
    v = jr.normal(jr.fold_in(key, 1), (batch, m), jnp.float32)
    return q, v


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=131072)
    ap.add_argument("--m", type=int, default=73)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    b, m = args.batch, args.m
    prec = pipe.MATMUL_PRECISION

    def jit(f):
        def wrapped(*a):
            with jax.default_matmul_precision(prec):
                return f(*a)

        return jax.jit(wrapped)

    factor = jit(jax.vmap(lambda q: jax.scipy.linalg.cho_factor(q, lower=True)[0]))
    solve = jit(
        jax.vmap(lambda c, v: jax.scipy.linalg.cho_solve((c, True), v))
    )  # fmt: skip
    subst = jit(jax.vmap(substitution_solve))
    unc = jit(jax.vmap(_solvers.unconstrained))
    unc_sub = jit(
        jax.vmap(lambda q, v: -substitution_solve(_solvers.cho_factor(q)[0], v))
    )  # fmt: skip
    gram = jit(lambda q: jnp.einsum("bki,bkj->bij", q, q))
    variants = {
        "cho_factor": (factor, lambda q, v, c: (q,)),
        "cho_solve": (solve, lambda q, v, c: (c, v)),
        "substitution": (subst, lambda q, v, c: (c, v)),
        "unconstrained": (unc, lambda q, v, c: (q, v)),
        "unconstrained_substitution": (unc_sub, lambda q, v, c: (q, v)),
        "gram": (gram, lambda q, v, c: (q,)),
    }
    report = {
        "device": str(jax.devices()[0].device_kind),
        "batch": b,
        "m": m,
        "matmul_gflops_f32": matmul_gflops(
            1024 if jax.default_backend() == "cpu" else 8192
        ),
    }
    inputs = []
    for r in range(args.repeats + 1):
        q, v = systems(jr.key(r), b, m)
        inputs.append((q, v, jax.block_until_ready(factor(q))))
    q0, v0, c0 = inputs[0]
    qn, vn = np.asarray(q0[:64], np.float64), np.asarray(v0[:64], np.float64)
    x_ref = np.linalg.solve(qn, vn[..., None])[..., 0]
    for name, (fn, args_of) in variants.items():
        out = jax.block_until_ready(fn(*args_of(q0, v0, c0)))  # compile
        times = []
        for q, v, c in inputs[1:]:
            a = args_of(q, v, c)
            t = time.perf_counter()
            jax.block_until_ready(fn(*a))
            times.append(time.perf_counter() - t)
        row = {"median_ms": 1e3 * statistics.median(times),
               "times_ms": [1e3 * t for t in times]}  # fmt: skip
        if name in ("cho_solve", "substitution"):
            x = np.asarray(out[:64], np.float64)
            row["rel_err"] = float(np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref))
        elif name.startswith("unconstrained"):
            x = -np.asarray(out[:64], np.float64)
            row["rel_err"] = float(np.linalg.norm(x - x_ref) / np.linalg.norm(x_ref))
        report[name] = row
        print(name, {k: v for k, v in row.items() if k != "times_ms"}, flush=True)
    print(json.dumps(report))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
