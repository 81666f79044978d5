"""Solve-only speed and accuracy of the per-pixel box QP: our active set against peers.

Every solver gets the same problems: the per-pixel systems $\\min \\tfrac12 x^TQx + q^Tx$,
$x \\ge 0$ of one ColorChecker sweep on the paper's rig (ideal sensor, true per-pixel
thresholds), assembled once in float64 by `pixel_system`. The reference answer is DAQP's
(exact dual active set, C, float64). Reported per solver: pixels per second of the
solve alone (median of `--repeats` runs in this process), and the SAM between its
answer and the reference (mean, 99.9th percentile, share within 0.1°). The same run's
float32 matmul GFLOP/s is printed beside it, so runs on different machines compare.

- `active-set (ours)`: `evhsi_jax`'s batched primal active set, float32 and float64,
  jitted over the batch (what `reconstruct` runs).
- `jaxopt BoxCDQP`: the reference solver of the README, vmapped, at its default budget
  (BoxOSQP, the other jaxopt solver, needs minutes for a few hundred pixels at its
  default 4000 iterations and is left out).
- `qpax` (JAX interior point, vmapped), `daqp`, `proxsuite` (dense ProxQP), `osqp`:
  the C/C++ solvers are called once per pixel from Python, which is how a user would
  batch them without writing C; their loop overhead is part of their time.

Peers are optional (`pip install -e '.[bench]'`); a missing one is skipped with a note.
Run: `.venv/bin/python experiments/bench_solvers.py [--size 48x72] [--repeats 3]`
→ experiments/results/bench_solvers.json.
"""

from __future__ import annotations

import argparse
import importlib
import json
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from _common import matmul_gflops

import evhsi_jax as ev
from evhsi_jax._model._illumination import band_table
from evhsi_jax._reconstruct import (
    PixelEvents,
    ProblemConfig,
    group_pixels,
    pixel_system,
)
from evhsi_jax._reconstruct._jaxopt import boxcdqp
from evhsi_jax._reconstruct._solvers import active_set_batch

OUT = Path(__file__).parent / "results" / "bench_solvers.json"


def problems(size, limit: int):
    """(Q, q) of up to `limit` pixels, float64 NumPy, shapes (n, M, M) and (n, M)."""
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", size)
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)
    with jax.enable_x64(True):
        r64 = rig.astype(jnp.float64)
        table = band_table(r64).channels(r64.grid.sub)
        offs = np.asarray(r64.column_offsets(events.width))
        batches, _, _ = group_pixels(events, chunk_pixels=512)
        qs, vs = [], []
        system = jax.jit(
            jax.vmap(lambda px: pixel_system(r64, table, ProblemConfig(), px, 1)[:2])
        )
        for b in batches:
            v = b.pixel >= 0
            pix = b.pixel[v]
            px = PixelEvents.batch(
                jnp.asarray(np.where(b.mask[v], b.t_us[v], 0.0)),
                jnp.asarray(b.polarity[v], jnp.int32),
                jnp.asarray(b.mask[v]),
                jnp.asarray(offs[b.column[v]]),
                jnp.asarray(info.threshold_on.reshape(-1)[pix], jnp.float64),
                jnp.asarray(info.threshold_off.reshape(-1)[pix], jnp.float64),
            )
            q_mat, q_vec = system(px)
            qs.append(np.asarray(q_mat))
            vs.append(np.asarray(q_vec))
    q_mat, q_vec = np.concatenate(qs), np.concatenate(vs)
    return q_mat[:limit], q_vec[:limit]


def sam_deg(a, b):
    num = np.sum(a * b, axis=1)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    cos = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _per_pixel(fn):
    def run(q_mat, q_vec):
        return np.stack([fn(h, f) for h, f in zip(q_mat, q_vec)])

    return run


def _daqp(h, f):
    import daqp

    m = f.size
    x, _, flag, _ = daqp.solve(
        h, f, np.zeros((0, m)), np.full(m, 1e30), np.zeros(m), np.zeros(m, np.int32)
    )
    return np.asarray(x)


def _proxsuite(h, f):
    import proxsuite

    m = f.size
    res = proxsuite.proxqp.dense.solve(
        h, f, None, None, np.eye(m), np.zeros(m), np.full(m, 1e30),
        eps_abs=1e-9, eps_rel=0.0,
    )  # fmt: skip
    return np.maximum(res.x, 0.0)


def _osqp(h, f):
    import osqp
    import scipy.sparse as sp

    m = f.size
    prob = osqp.OSQP()
    prob.setup(
        sp.csc_matrix(np.triu(h)), f, sp.eye(m, format="csc"), np.zeros(m),
        np.full(m, np.inf), verbose=False, eps_abs=1e-9, eps_rel=1e-9,
        max_iter=20000, polishing=True,
    )  # fmt: skip
    return np.maximum(prob.solve().x, 0.0)


def _jax_batch(fn, dtype):
    jitted = jax.jit(jax.vmap(fn))

    def run(q_mat, q_vec):
        with jax.enable_x64(dtype == jnp.float64):
            x = jitted(jnp.asarray(q_mat, dtype), jnp.asarray(q_vec, dtype))
            return np.asarray(x, np.float64)

    return run


def _qpax(h, f):
    import qpax

    m = f.shape[0]
    return qpax.solve_qp_primal(
        h, f, jnp.zeros((0, m), h.dtype), jnp.zeros((0,), h.dtype),
        -jnp.eye(m, dtype=h.dtype), jnp.zeros(m, h.dtype),
    )  # fmt: skip


def _ours(dtype):
    spec = ev.reconstruction.SOLVERS["active-set"]
    jitted = jax.jit(
        lambda a, b: active_set_batch(a, b, tol=spec.tol, max_iters=spec.iters)[0]
    )

    def run(q_mat, q_vec):
        with jax.enable_x64(dtype == jnp.float64):
            x = jitted(jnp.asarray(q_mat, dtype), jnp.asarray(q_vec, dtype))
            return np.asarray(x, np.float64)

    return run


SOLVERS = {
    "active-set (ours), float32": (None, lambda: _ours(jnp.float32)),
    "active-set (ours), float64": (None, lambda: _ours(jnp.float64)),
    "daqp (C, float64)": ("daqp", lambda: _per_pixel(_daqp)),
    "proxsuite dense (C++, float64)": ("proxsuite", lambda: _per_pixel(_proxsuite)),
    "osqp (C, float64)": ("osqp", lambda: _per_pixel(_osqp)),
    "qpax (JAX, float32)": ("qpax", lambda: _jax_batch(_qpax, jnp.float32)),
    "qpax (JAX, float64)": ("qpax", lambda: _jax_batch(_qpax, jnp.float64)),
    "jaxopt BoxCDQP (float32)": (None, lambda: _jax_batch(boxcdqp, jnp.float32)),
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="48x72")
    ap.add_argument("--pixels", type=int, default=1024, help="problems solved per run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    size = ev.forward.parse_size(args.size)
    q_mat, q_vec = problems(size, args.pixels)
    n = q_mat.shape[0]
    gflops = matmul_gflops()
    ref = _per_pixel(_daqp)(q_mat, q_vec) if _available("daqp") else None
    if ref is None:
        with jax.enable_x64(True):
            ref = _ours(jnp.float64)(q_mat, q_vec)
    rows = []
    for name, (module, make) in SOLVERS.items():
        if module and not _available(module):
            print(f"{name:34s} skipped: `{module}` not installed (pip install -e '.[bench]')")
            continue
        run = make()
        run(q_mat, q_vec)  # compile (the JAX solvers) / warm up
        times, x = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            x = run(q_mat, q_vec)
            times.append(time.perf_counter() - t0)
        s = sam_deg(x, ref)
        row = {
            "solver": name,
            "px_per_s": n / statistics.median(times),
            "sam_mean_deg": float(np.mean(s)),
            "sam_p999_deg": float(np.quantile(s, 0.999)),
            "within_0p1_deg": float(np.mean(s <= 0.1)),
        }
        rows.append(row)
        print(
            f"{name:34s} {row['px_per_s']:10,.0f} px/s   SAM to reference mean "
            f"{row['sam_mean_deg']:.3f}°, 99.9 % {row['sam_p999_deg']:.3f}°, "
            f"{100 * row['within_0p1_deg']:.1f} % within 0.1°",
            flush=True,
        )
    ours = rows[0]["px_per_s"]
    for r in rows:
        r["relative_to_ours_float32"] = r["px_per_s"] / ours
    result = {
        "setup": {
            "size": list(size),
            "pixels": n,
            "channels": int(q_vec.shape[1]),
            "repeats": args.repeats,
            "reference": "daqp float64" if _available("daqp") else "ours float64",
            "float32_matmul_gflops": gflops,
            "devices": str(jax.devices()),
        },
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"float32 matmul {gflops:.1f} GFLOP/s in this run; wrote {out}")


def _available(module: str) -> bool:
    try:
        importlib.import_module(module)
        return True
    except ImportError:
        return False


if __name__ == "__main__":
    main()
