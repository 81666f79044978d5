"""The fused CPU path: each pixel's system assembled from band segments and solved
where it is formed (numba), on every core.

The JAX path forms every pixel's rows densely (M+1 wide), their Gram matrix by a
batched matrix product and then solves; on a CPU the dense Gram is most of the time,
although a row touches only the channels the band overlaps at its two or three times
(~16 of 72 on the paper's rig). Here, per pixel and in float64:

1. each row is added into Q as the outer product of its *span* (the channels where its
   bands are above `BAND_TRIM` (1e-7) × the band's own peak, `BandTable.trimmed`),
   Q's envelope (the first touched column of each row) tracked as it grows;
2. the spectral prior (banded for `spec_kind="d2"`) and the ridge are added;
3. an *envelope* Cholesky (fill-in stays inside the envelope) gives the unconstrained
   minimiser; where a bound is violated the primal active-set method of
   :func:`._solvers.active_set_batch` runs with the same steps and tolerance.

The arithmetic is float64 whatever the rig's dtype (a float32 input is exact in it):
this is the issue's "mixed precision", and it makes the answer the float64 solve of
the same events rather than one defined by the rounding of a float32 Gram matrix with
cond(Q) up to ~1e8. Entries of a band (a row of the band table) below 1e-7 of that
band's peak are treated as zero (`BandTable.trimmed`; the `cuda` backend solves with
the same trimmed table), and so are a photoreceptor row's below 1e-7 of its largest;
that is the only difference to the dense problem of :func:`._problem.pixel_system` in
float64 (tests compare the two: ≤ 0.002° SAM on the tests' scenes; the trim narrows
Q's envelope).

Scope: the whole per-pixel problem `reconstruct` solves with the active-set solver
and the linear table lookup — the ideal sensor's, and with a calibrated noise model
the noise-aware one: event times moved back by the photoreceptor's lag, rows weighted
by their noise, the dark-channel prior, the photoreceptor model relinearised at the
answer (Gauss–Newton passes, any number of sweeps; its filter runs as $F = S V$
with a running scale so a time step costs the band's span) and the robust
reweighting. Other solvers, the cubic lookup, gradients and accelerators stay on the
JAX path (:func:`fused_supported`). Threads: pixels are handed out in blocks to `threads`
workers (:func:`block_pixels`); the kernel releases the GIL. With the photoreceptor
rows the pixels go column by column (the answers come back in the caller's order):
the band on a column's time grid is then formed once per column, not per pixel
(1.25× the realistic kernel, `experiments/bench_kernel_ab.py --sensor realistic`).
"""

from __future__ import annotations

import concurrent.futures
import threading

import numpy as np

from .._base import numba_available, readonly, shard
from .._model import Rig, trim_rows
from ._problem import (
    INT_TARGETS,
    ProblemConfig,
    dark_strength,
    lit_interval_us,
    spectral_prior_matrix,
)

__all__ = ["fused_supported", "FusedProblem", "solve_fused"]

#: The most pixels handed to a worker at a time. A block costs ~70 µs of one core
#: beyond its pixels' work (blocks of 128 against 4096 ideal pixels on one thread;
#: numba's dispatch of ~20 arrays, the kernel's ~1 MB of zeroed work space, the
#: answers' copy into the cube — not timed one by one). Blocks of 512 (~6 ms of
#: ideal pixels) made whole ideal sweeps 1.00–1.035× as long as these (medians of the
#: per-round ratios), within the machine's spread (`experiments/bench_blocks.py`;
#: Performance log, "Twentieth session"); the answers are the same to the bit.
BLOCK_PIXELS = 2048
#: The fewest, unless there are fewer pixels: small images still split into
#: `BLOCKS_PER_THREAD` blocks per worker, so the workers finish together.
MIN_BLOCK_PIXELS = 256
BLOCKS_PER_THREAD = 16


def block_pixels(n: int, threads: int) -> int:
    """Pixels per block for `n` pixels on `threads` workers: ~`BLOCKS_PER_THREAD`
    blocks per worker, within [`MIN_BLOCK_PIXELS`, `BLOCK_PIXELS`] (the upper bound
    wins)."""
    per = -(-n // (BLOCKS_PER_THREAD * max(1, threads)))
    return int(max(1, min(BLOCK_PIXELS, max(MIN_BLOCK_PIXELS, per))))


def row_spans(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(lo, hi)`: each row's (last axis of the boolean `mask`) first True column and
    one past its last, int64; `(m, 0)` for a row without one."""
    m = mask.shape[-1]
    has = mask.any(axis=-1)
    lo = np.where(has, np.argmax(mask, axis=-1), m)
    hi = np.where(has, m - np.argmax(mask[..., ::-1], axis=-1), 0)
    return lo.astype(np.int64), hi.astype(np.int64)


def fused_supported(spec, cfg: ProblemConfig) -> str | None:
    """Why the fused path cannot run this reconstruction (None: it can)."""
    if not numba_available():
        return "numba is not available"
    if spec.name != "active-set":
        return f"solver {spec.name!r} (the fused path is the active-set solver)"
    if cfg.lookup_order != 1:
        return "lookup_order 3"
    if not cfg.nonneg:
        return "nonneg=False (the fused path solves the box QP)"
    return None


class FusedProblem:
    """The rig- and configuration-dependent inputs of the kernel, built once.

    `lanes`: pixels whose systems are factorised side by side (4, the default; 1: one
    pixel at a time, the reference the tests compare with). `long_rows`: with four
    lanes, the event rows that span far more than a band (`_fused_jit.LONG_SPAN`: a
    sweep's first event against a reference in the sweep before) are left out of Q's
    envelope and added by the Woodbury identity (the default; False adds them to Q
    like every other row, as the one-pixel kernel does)."""

    def __init__(self, rig: Rig, table, cfg: ProblemConfig, spec, width: int,
                 column_offsets_us: np.ndarray, sweeps: int, noise=None, *,
                 lanes: int | None = None, long_rows: bool = True):  # fmt: skip
        from . import _fused_jit as jit  # (numba: only when the fused path runs)

        if lanes not in (None, 1, jit.LANES):
            raise ValueError(f"lanes must be 1 or {jit.LANES}, got {lanes!r}")

        # Each band's span: its channels above BAND_TRIM of its own peak (the CUDA
        # backend's rows come from the same trimmed table).
        tab = trim_rows(np.asarray(table.values, np.float64))
        m = tab.shape[1]
        self.span_lo, self.span_hi = row_spans(tab != 0.0)
        self.table = np.ascontiguousarray(tab)
        self.tabsum = tab.sum(axis=1)
        s = spectral_prior_matrix(m, cfg.m_start_frac, cfg.spec_kind)
        nz = np.abs(s) > 0
        self.spec = np.ascontiguousarray(s)
        self.spec_first = np.where(
            nz.any(axis=1), np.argmax(nz, axis=1), np.arange(m)
        ).astype(np.int64)
        self.spec_first = np.minimum(self.spec_first, np.arange(m))
        f = lambda v: float(np.asarray(v))  # noqa: E731
        speed = f(rig.band_speed_nm_per_us)
        arrive, leave = (f(v) for v in lit_interval_us(rig, 0.0))
        par = np.zeros(jit.N_PAR)
        par[:19] = [
            f(rig.baseline_level), f(rig.refractory_us), f(rig.period_us), speed,
            f(rig.sweep_start_nm), f(rig.sweep_curvature_nm),
            0.5 * (rig.grid.start_nm + rig.grid.stop_nm),
            0.5 * (rig.grid.stop_nm - rig.grid.start_nm),
            arrive, leave, rig.grid.width_nm / speed, cfg.alpha_int / sweeps,
            cfg.alpha_spec,
            cfg.ridge, cfg.peak_height, spec.tol, float(np.trace(s)),
            float(table.lo_nm), 1.0 / float(table.step_nm),
        ]  # fmt: skip
        # The noise model [σ_C, σ_t, d_w] and the reweighting's settings.
        nz = np.zeros(3) if noise is None else np.asarray(noise, np.float64)
        par[19:29] = [
            nz[0], nz[1], nz[2], cfg.noise_floor, dark_strength(sweeps, cfg),
            cfg.robust_c,
            cfg.robust_reject, f(rig.baseline_rel), f(rig.log_eps), cfg.lowpass_tol,
        ]  # fmt: skip
        # Reciprocals of the period and of the grid's half width: the band lookups
        # multiply instead of dividing (two divisions per lookup, ~100 lookups per
        # pixel).
        par[jit.P_INV_PERIOD] = 1.0 / par[jit.P_PERIOD]
        par[jit.P_INV_HALF] = 1.0 / par[jit.P_HALF]
        self.par = par
        # The photoreceptor rows run (as the kernel decides, `lowpass`): the kernel
        # then forms each column's time grid once for the column's pixels, so the
        # pixels go to it column by column (solve_fused).
        self.lowpass = bool(
            noise is not None and nz[2] > 0 and cfg.lowpass_passes > 0
        )
        self.ipar = np.array(
            [sweeps, cfg.int_points, INT_TARGETS.index(cfg.int_target),
             int(cfg.normalise), int(rig.reset_mode == "release"), spec.iters,
             int(noise is not None), cfg.robust_steps, cfg.lowpass_passes,
             int(rig.samples_per_sweep), jit.LANES if lanes is None else lanes,
             int(long_rows)],
            np.int64,
        )  # fmt: skip
        # Dark-channel prior: per neighbour difference, ½(dim_k + dim_k+1), dim the
        # peak light over the channel's light − 1 (capped), as in pixel_system.
        light = tab.max(axis=0)
        dim = np.minimum(light.max() / np.maximum(light, 1e-12) - 1.0, 1e4)
        self.dark = np.ascontiguousarray(0.5 * (dim[1:] + dim[:-1]))
        self.width = int(width)
        self.col_off = np.ascontiguousarray(column_offsets_us, np.float64)
        self.channels = m

    def kernel_order(self, sel: np.ndarray) -> np.ndarray | None:
        """The permutation that puts the flat pixel indices `sel` in the order the
        kernel takes them — column by column, stable, when the photoreceptor rows run
        (`lowpass`) — or None when `sel` already is in it (a caller that lists its
        pixels so gets its answers without their being moved back)."""
        if not self.lowpass or sel.size < 2:
            return None
        col = sel % self.width
        if not np.any(col[1:] < col[:-1]):
            return None
        return np.argsort(col, kind="stable")


def kernel_inputs(prob: FusedProblem, starts, use, t_sorted, s_sorted, lead, thr_on,
                  thr_off) -> tuple:  # fmt: skip
    """The arguments of the kernel's `solve_pixels` between `sel` and the outputs,
    each a contiguous *read-only* array (`readonly`): numba compiles one version of
    the kernel per argument type, and an array's writeable flag is part of its type.
    NumPy views of JAX arrays (a float64 rig's band table, its offsets) are read-only
    while copies are not, so without this a float64 reconstruction compiled the whole
    kernel a second time (~20 s on a clean clone)."""
    f, i = np.float64, np.int64
    return (
        readonly(starts, i), readonly(use, i), readonly(t_sorted, f),
        readonly(s_sorted, np.int8), readonly(lead, f), readonly(prob.col_off, f),
        np.int64(prob.width), readonly(thr_on, f), readonly(thr_off, f),
        readonly(prob.table, f), readonly(prob.tabsum, f), readonly(prob.span_lo, i),
        readonly(prob.span_hi, i), readonly(prob.spec, f), readonly(prob.spec_first, i),
        readonly(prob.dark, f), readonly(prob.par, f), readonly(prob.ipar, i),
    )  # fmt: skip


def solve_fused(
    prob: FusedProblem,
    sel: np.ndarray,
    starts: np.ndarray,
    use: np.ndarray,
    t_sorted: np.ndarray,
    s_sorted: np.ndarray,
    lead: np.ndarray,
    thr_on: np.ndarray,
    thr_off: np.ndarray,
    *,
    threads: int | None = None,
    progress=None,
    out: tuple[np.ndarray, np.ndarray] | None = None,
    fit: np.ndarray | None = None,
):
    """Solve pixels `sel` (flat indices) from their events in pixel order (CSR:
    `starts`, `use`). Returns `(x (n, M) float64, kkt (n,), steps (n,))`; a pixel whose
    factorisation failed has NaN x and steps −1.

    `out=(cube, kkt_all)`: the answers go into rows `sel` of these arrays (e.g. the
    float32 cube, `(pixels, M)`, and its KKT residuals) as each block of pixels is
    solved, by the worker that solved it; `x` and `kkt` are then returned as None.
    A whole sweep's float64 answers are then never held at once (1280×720: 531 MB,
    written, then copied into the cube by one thread).

    `fit`: an `(n, 3)` float64 array for each pixel's fit to its event rows, in the
    order of `sel` (the kernel's `out_fit`: largest |residual| in σ, its event index,
    capped sum of squares; NaN without the noise model)."""
    from . import _fused_jit as jit

    n, m = sel.size, prob.channels
    steps = np.empty(n, np.int64)
    args = kernel_inputs(prob, starts, use, t_sorted, s_sorted, lead, thr_on, thr_off)
    sel = np.ascontiguousarray(sel, np.int64)
    back = prob.kernel_order(sel)  # (see FusedProblem.lowpass)
    if back is not None:
        sel = sel[back]
    sel = readonly(sel, np.int64)  # (one kernel type: see kernel_inputs)
    fits = np.empty((n, 3)) if fit is None else fit  # (the caller's, written there)
    if out is None:
        x, kkt = np.empty((n, m)), np.empty(n)
    else:
        x = kkt = None
        scratch = threading.local()  # each worker's block of answers, reused

    threads = shard.usable_cores() if threads is None else max(1, int(threads))
    block = block_pixels(n, threads)

    def run(lo):
        hi = min(lo + block, n)
        if out is None:
            jit.solve_pixels(
                sel[lo:hi], *args, x[lo:hi], kkt[lo:hi], steps[lo:hi], fits[lo:hi]
            )
            return hi - lo
        if getattr(scratch, "x", None) is None:
            scratch.x, scratch.kkt = np.empty((block, m)), np.empty(block)
        xb, kb = scratch.x[: hi - lo], scratch.kkt[: hi - lo]
        jit.solve_pixels(sel[lo:hi], *args, xb, kb, steps[lo:hi], fits[lo:hi])
        rows = sel[lo:hi]
        if np.all(np.diff(rows) == 1):  # consecutive pixels: a slice, not a scatter
            rows = slice(int(rows[0]), int(rows[-1]) + 1)
        out[0][rows] = xb
        out[1][rows] = kb
        return hi - lo

    blocks = range(0, n, block)
    if threads == 1 or n <= block:
        for lo in blocks:
            done = run(lo)
            if progress is not None:
                progress(done)
    else:
        with concurrent.futures.ThreadPoolExecutor(threads) as pool:
            for done in pool.map(run, blocks):
                if progress is not None:
                    progress(done)
    if back is not None:  # the answers in the caller's order of `sel`
        steps[back] = steps.copy()
        fits[back] = fits.copy()
        if out is None:
            x[back], kkt[back] = x.copy(), kkt.copy()
    return x, kkt, steps
