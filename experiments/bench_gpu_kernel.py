"""The GPU path's CUDA kernel (`_reconstruct/_cuda_kernel.py`: Gram, priors and box QP
of each pixel in one thread block's shared memory) against the JAX path's batched Gram
and cuSOLVER Cholesky, on the same rows.

Setup: the paper rig, one sweep of the ColorChecker at `--size` (default 720×1280),
simulated, screened and cut into chunks as `ev.reconstruct` cuts them on the device
(`batch_sizes`), the sensor's true thresholds (as after a calibration), ideal sensor,
float32, solver `auto` (active set, 48 steps, tol 1e-6). Timed on the device, each the
median of `--repeats` warm runs in one process (inputs already on the device):

- `jax_device_s`: `_pipeline._solve_chunk` of every chunk (rows, Gram, Cholesky and
  active set: the device work of the README's one-GPU table);
- `rows_s`: the rows alone (`pixel_system(..., return_rows=True)`, vmapped, jitted);
- `kernel_s`: the CUDA kernel on those rows (Gram + priors + box QP), its registers
  and memory (`kernel_resources`), and `variants` (`--variants`): Q kept in shared
  memory or in a global scratch (`_cuda_kernel.Q_GLOBAL`, the default since the
  session of 2026-11-26, seventh), register caps, the next pass's rows read ahead
  (`pf`, `_cuda_kernel.PREFETCH`) — each one's time, resources and whether its
  answers are the same as the default kernel's;

and the accuracy of both answers against a float64 solve of the same float32 rows
(`--check` pixels drawn at random; `_fused_jit._box_qp` in float64 on the host):
the share within 0.1° SAM, median and max, and the SAM of each to the truth. The
same run's float32 matmul GFLOP/s (default precision) is reported beside them.

    python experiments/bench_gpu_kernel.py [--size 720x1280] [--repeats 5]
        [--check 20000] [--out experiments/results/bench_gpu_kernel.json]
        [--variants shared:none,shared:none:pf] [--save-rows rows.npz]

`--save-rows NPZ` also writes one chunk's rows, the input of
`profile_gpu_kernel.py` (a profiler attached to a process without JAX).

On a CPU, `NUMBA_ENABLE_CUDASIM=1` runs the kernel in numba's simulator: use a tiny
`--size` and `--limit` (a few pixels; minutes per hundred pixels).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from _common import device_header, write_json

import evhsi_jax as ev
from evhsi_jax._base import njit
from evhsi_jax._model import band_table
from evhsi_jax._reconstruct import _cuda_kernel as ck
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct._fused_jit import _box_qp
from evhsi_jax._reconstruct._pixels import group_pixels
from evhsi_jax._reconstruct._problem import (
    ProblemConfig,
    pixel_system,
    spectral_prior_matrix,
)


def median_time(fn, repeats):
    out = fn()  # warm-up (compilation)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, statistics.median(times), times


@njit
def reference(ev_rows, drift, spec_w, spec, ridge_rel, tol, iters):
    """float64 box-QP answers of the pixels' rows (dense envelope), as the fused CPU
    path solves them."""
    n, _, m1 = ev_rows.shape
    m = m1 - 1
    out = np.zeros((n, m))
    first = np.zeros(m, np.int64)
    free = np.ones(m, np.bool_)
    lf = np.zeros((m, m))
    inv = np.zeros(m)
    p = np.zeros(m)
    gr = np.zeros(m)
    x = np.zeros(m)
    trs = np.trace(spec)
    for b in range(n):
        r = ev_rows[b].astype(np.float64)
        d = drift[b].astype(np.float64)
        gram = r.T @ r + d.T @ d
        qm = gram[:m, :m].copy()
        qv = gram[:m, m].copy()
        tr = 0.0
        for i in range(m):
            tr += qm[i, i]
        ridge = ridge_rel * ((tr + spec_w[b] * trs) / m + 1e-30)
        for i in range(m):
            for j in range(m):
                qm[i, j] += spec_w[b] * spec[i, j]
            qm[i, i] += ridge
        for i in range(m):
            first[i] = 0
        steps = _box_qp(qm, qv, first, free, lf, inv, x, p, gr, tol, iters, False)
        for i in range(m):
            out[b, i] = x[i] if steps >= 0 else np.nan
    return out


def sam_deg(a, b):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    c = np.sum(a * b, axis=-1) / np.maximum(na * nb, 1e-300)
    d = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return np.where((na == 0) & (nb == 0), 0.0, d)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--check", type=int, default=20000)
    ap.add_argument(
        "--variants", default="shared:none,shared:none:pf,shared:64",
        help="kernel variants to time, PLACE:REGS[:pf|nopf] (shared|global, a "
        "register cap or none; pf / nopf: the next pass's rows read ahead or not)",
    )  # fmt: skip
    ap.add_argument(
        "--save-rows", default="", metavar="NPZ",
        help="also save one chunk's rows (--save-rows-chunk) for profile_gpu_kernel.py",
    )  # fmt: skip
    ap.add_argument("--save-rows-chunk", default="3:32768", metavar="CHUNK:PIXELS")
    ap.add_argument("--limit", type=int, default=0, help="pixels per chunk (simulator)")
    ap.add_argument("--out", default="experiments/results/bench_gpu_kernel.json")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    report = {**device_header(h, w), "simulated_cuda": ck.simulated()}
    print(report, flush=True)
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", (h, w))
    truth = np.asarray(scene.truth_cube(rig.grid)).reshape(h * w, -1)
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)
    maps = (np.asarray(info.threshold_on), np.asarray(info.threshold_off))
    chunk, sub = pipe.batch_sizes(None, None)
    screened = pipe.screen_events(events, rig, 0, None, 1, None)[0]
    batches, _, _ = group_pixels(
        screened, t_start_us=0, chunk_pixels=chunk, min_chunk=sub,
        merge_below=chunk // 4,
    )  # fmt: skip
    dtype = rig.fwhm_nm.dtype
    offs = np.asarray(rig.column_offsets(w), np.float64)
    on, off = (np.asarray(mp, np.float64).reshape(-1) for mp in maps)
    pxs, pixels = [], []
    for b in batches:
        keep = slice(None) if not args.limit else slice(0, args.limit)
        pix = np.where(b.pixel >= 0, b.pixel, 0)[keep]
        pxs.append(pipe._device_pixels(  # as reconstruct puts a batch on the device
            b.t_us[keep], b.polarity[keep], b.mask[keep], pix, b.column[keep],
            np.zeros(pix.shape), offs, on, off, np.dtype(dtype),
        ))  # fmt: skip
        pixels.append(np.asarray(b.pixel)[keep])
    report["chunks"] = [list(p.t_us.shape) for p in pxs]
    print("chunks", report["chunks"], flush=True)
    table = band_table(rig).channels(rig.grid.sub)
    cfg = ProblemConfig()
    spec_solver = pipe.solver_spec("auto")
    m = table.values.shape[1]
    prior = spectral_prior_matrix(m, cfg.m_start_frac, cfg.spec_kind)

    def jax_device():
        outs = [
            pipe._solve_chunk(
                rig, table, cfg, spec_solver, min(sub, p.t_us.shape[0]), p, 1
            )
            for p in pxs
        ]
        return jax.block_until_ready(outs)

    @jax.jit
    def rows_of(px):
        with jax.default_matmul_precision(pipe.MATMUL_PRECISION):
            return jax.vmap(
                lambda one: pixel_system(rig, table, cfg, one, 1, return_rows=True)
            )(px)

    def rows_all():
        return jax.block_until_ready([rows_of(p) for p in pxs])

    counts = jax.block_until_ready(
        [jnp.sum(p.mask, axis=1, dtype=jnp.int32) for p in pxs]
    )

    def kernel(rows, iters=spec_solver.iters, **variant):
        return [
            ck.solve_rows(r, n, prior, cfg.ridge, spec_solver.tol, iters, **variant)
            for r, n in zip(rows, counts, strict=True)
        ]

    variants = {v: ck.variant(v) for v in filter(None, args.variants.split(","))}
    if args.save_rows:  # one chunk's rows for profile_gpu_kernel.py (no JAX there)
        i, n = (int(v) for v in args.save_rows_chunk.split(":"))
        r = rows_of(pxs[i])
        np.savez(
            args.save_rows, events=np.asarray(r.events[:n]),
            drift=np.asarray(r.drift[:n]), spec_weight=np.asarray(r.spec_weight[:n]),
            counts=np.asarray(counts[i][:n]), prior=np.asarray(prior, np.float32),
            ridge=float(cfg.ridge), tol=float(spec_solver.tol),
            iters=int(spec_solver.iters),
        )  # fmt: skip
        print("saved", args.save_rows, "chunk", i, "pixels", n, flush=True)

    def host(a):
        return a.copy_to_host() if hasattr(a, "copy_to_host") else np.asarray(a)

    jx, t_jax, times_jax = median_time(jax_device, args.repeats)
    print("jax device work", t_jax, flush=True)
    rows, t_rows, times_rows = median_time(rows_all, args.repeats)
    print("rows", t_rows, flush=True)
    kx, t_kern, times_kern = median_time(lambda: kernel(rows), args.repeats)
    print("kernel", t_kern, flush=True)
    # The same without active-set steps (clipped unconstrained minimisers): what the
    # steps cost.
    _, t_kern0, _ = median_time(lambda: kernel(rows, 0), args.repeats)
    report["kernel_resources"] = ck.resources(m)
    print("kernel resources", report["kernel_resources"], flush=True)
    # Variants (`--variants`, each `PLACE:REGS[:pf|nopf]`: Q in shared memory or a
    # global scratch, a register cap or none, the rows read ahead or not): time,
    # resources, whether the answers are the same.
    report["variants"] = {}
    for var, kw in variants.items():
        try:
            ko, t_v, times_v = median_time(
                lambda kw=kw: kernel(rows, **kw), args.repeats
            )  # fmt: skip
        except Exception as err:
            report["variants"][var] = {"error": repr(err)[:300]}
            print("variant", var, "failed", repr(err)[:300], flush=True)
            continue
        same = all(
            np.array_equal(host(a[0]), host(b[0]), equal_nan=True)
            for a, b in zip(kx, ko, strict=True)
        )
        report["variants"][var] = {
            "s": t_v, "times": times_v, "same_answers": same,
            **ck.resources(m, **kw),
        }  # fmt: skip
        print("variant", var, report["variants"][var], flush=True)
    report.update(
        jax_device_s=t_jax, rows_s=t_rows, kernel_s=t_kern, kernel_no_steps_s=t_kern0,
        times={"jax": times_jax, "rows": times_rows, "kernel": times_kern},
        px_per_s_jax=h * w / t_jax, px_per_s_rows_kernel=h * w / (t_rows + t_kern),
    )  # fmt: skip
    print({k: v for k, v in report.items() if k != "times"}, flush=True)

    # Accuracy on a random sample of the solved pixels (the same share per chunk).
    rng = np.random.default_rng(0)
    n_all = sum(len(pp) for pp in pixels)
    parts = {"kernel": [], "jax": [], "x64": [], "pix": []}
    steps_real = []
    t = time.perf_counter()
    for (xk, _, sk), (xj, _), r, n, pp in zip(
        kx, jx, rows, counts, pixels, strict=True
    ):
        real = np.flatnonzero(pp >= 0)
        steps_real.append(host(sk)[real])
        n_pick = min(real.size, max(1, round(args.check * len(pp) / n_all)))
        pick = np.sort(rng.choice(real, n_pick, replace=False))
        idx = jnp.asarray(pick)
        used = np.arange(r.events.shape[1])[None, :] < np.asarray(n)[pick][:, None]
        x64 = reference(
            np.asarray(r.events[idx]) * used[:, :, None],
            np.asarray(r.drift[idx]), np.asarray(r.spec_weight[idx], np.float64),
            prior.astype(np.float64), float(cfg.ridge), float(spec_solver.tol),
            int(spec_solver.iters),
        )  # fmt: skip
        parts["kernel"].append(host(xk)[pick])
        parts["jax"].append(np.asarray(xj)[pick])
        parts["x64"].append(x64)
        parts["pix"].append(pp[pick])
    ref_s = time.perf_counter() - t
    x64 = np.concatenate(parts["x64"])
    pick_pix = np.concatenate(parts["pix"])
    steps_real = np.concatenate(steps_real)
    tr = truth[pick_pix]
    acc = {"pixels": int(pick_pix.size), "reference_s": ref_s}
    for name in ("kernel", "jax"):
        xs = np.concatenate(parts[name])
        d = sam_deg(xs, x64)
        acc[name] = {
            "share_within_0.1deg": float(np.mean(d <= 0.1)),
            "median_deg": float(np.nanmedian(d)),
            "max_deg": float(np.nanmax(d)),
            "nan": int(np.sum(~np.isfinite(xs).all(axis=1))),
            "sam_to_truth_deg": float(np.nanmean(sam_deg(xs, tr))),
        }
    acc["float64_sam_to_truth_deg"] = float(np.nanmean(sam_deg(x64, tr)))
    acc["kernel_active_set_steps_mean"] = float(np.mean(steps_real))
    acc["kernel_share_with_steps"] = float(np.mean(steps_real > 0))
    acc["kernel_failed"] = int(np.sum(steps_real < 0))
    report["accuracy"] = acc
    print("accuracy", json.dumps(acc, indent=1), flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
