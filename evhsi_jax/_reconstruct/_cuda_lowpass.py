"""CUDA kernel of the photoreceptor pass's rows on the GPU path (`backend="cuda"`).

With a photoreceptor low-pass in the noise model, the reconstruction solves once with
delay-shifted events, then replaces each event row by the low-passed sensor model
linearised at that answer (Gauss–Newton passes, :func:`._problem._lowpass_rows`).
JAX forms those rows by running the filter on the rig's whole time grid for every
pixel at once: a `(pixels, grid, M+1)` array through an associative scan, ~1,200
grid points per sweep — on an H100 most of the realistic sweep's time (experiments/
PERFORMANCE_LOG.md, "The path a real rig runs, on a GPU").

Here one warp walks one pixel's grid in order, each thread holding the filter's state
for its own entries of `[log, g_1 … g_M]` in registers, so nothing of the grid goes
through memory:

1. at each grid point the band's table row and fraction (the same linear lookup as
   :func:`evhsi_jax._model.lookup`, from the column's offset and the sweep's
   curvature), the intensity at the linearisation point (a warp sum), its logarithm,
   the filter's decay, and the update of the thread's entries (the Jacobian's
   entries take the band with the log's slope plus the decay's part, which needs
   the filtered log at the point before: every thread keeps that scalar);
2. the event times and the releases after them (the two ends of each event's row)
   are two ascending streams of queries: when the walk passes a query's grid
   interval, the filtered state there (linear interpolation between grid points)
   is added to (event) or subtracted from (release) the row, in the output array;
3. the walk stops at the last query; then each row gets its constant part
   $ΔF_{L_0} - ΔF_g\\cdot x_0 - σ_k C$ (a warp sum) and the noise weight of its
   event.

The rows are those of `pixel_system(..., x0=x)` (float32; the filter runs as a
recursion instead of JAX's scan, so they differ by rounding: tested against it in
numba's CUDA simulator, `tests/reconstruction/test_cuda_kernel.py`). Only the linear
table lookup (`lookup_order=1`); the pipeline keeps JAX's rows otherwise.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import cuda, float32, int32

from ._cuda_kernel import CACHE, THREADS, _kernel_jit, as_cuda, simulated

#: Pixels (warps) per thread block on a GPU.
PIXELS_PER_BLOCK = 4
#: Threads per pixel under the simulator (its barriers are slow).
SIM_THREADS = 4
#: Entries of the rig-dependent parameter vector `par` (see :func:`lowpass_params`).
N_PAR = 13


@functools.cache
def make_lowpass_kernel(m: int, nt: int = THREADS, ppb: int = PIXELS_PER_BLOCK):
    """The kernel for M = `m` channels, `nt` threads per pixel and `ppb` pixels per
    block (compile-time). On a GPU `nt` is 32 (warp shuffles); the simulator takes
    any `nt` with `ppb` = 1 (its sums go through shared memory with barriers)."""
    m1 = m + 1
    nv = -(-m1 // nt)  # filter entries per thread
    sim = simulated()

    if sim:

        @cuda.jit(device=True)
        def wsum(v, t, buf, y):
            buf[y, t] = v
            cuda.syncthreads()
            r = float32(0.0)
            for s in range(nt):
                r += buf[y, s]
            cuda.syncthreads()
            return r

    else:

        @cuda.jit(device=True)
        def wsum(v, t, buf, y):
            for off in (16, 8, 4, 2, 1):
                v += cuda.shfl_xor_sync(0xFFFFFFFF, v, off)
            return v

    @cuda.jit(device=True, inline=True)
    def grid_pos(tq, t0, dt, g_last):
        """(i, f): the grid interval [i, i + 1] of time `tq` and the fraction in it,
        as `_lowpass_rows`' interpolation (clipped to the grid)."""
        pos = min(max((tq + t0) / dt, float32(0.0)), g_last)
        i = min(max(int32(math.floor(pos)), int32(0)), int32(g_last) - int32(1))
        return i, pos - float32(i)

    @cuda.jit(device=True, inline=True)
    def band_at(j, t0, off, par, n_tab):
        """(row, fraction, inside) of the band table at grid point j of a pixel with
        clock shift t0 and column offset `off` (`_problem.pixel_system`'s `a_at`)."""
        period = par[0]
        tg = float32(j) * par[1] - t0
        loc = math.fmod(tg + t0, period)
        if loc < 0.0:
            loc += period
        loc = math.fmod(loc, period)  # (band_centre_nm's own mod)
        if loc < 0.0:
            loc += period
        lin = par[5] + par[6] * (loc + off)
        z = (lin - par[8]) / par[9]
        centre = lin + par[7] * (float32(1.0) - z * z)
        pos = (centre - par[10]) / par[11]
        top = float32(n_tab - 1)
        inside = pos >= 0.0 and pos <= top
        pos = min(max(pos, float32(0.0)), top)
        i0 = min(max(int32(math.floor(pos)), int32(0)), int32(n_tab - 2))
        return i0, pos - float32(i0), inside

    @_kernel_jit(cuda.jit, {}, CACHE and not sim)
    def kernel(t_us, pol, ev_n, thr_on, thr_off, t0p, col_off, x0, w_log, table, par,
               g_n, out):  # fmt: skip
        t = cuda.threadIdx.x
        b = cuda.blockIdx.x * ppb + cuda.threadIdx.y
        if b >= out.shape[0]:  # (a whole warp: b is the warp's)
            return
        buf = cuda.shared.array((ppb, nt), float32)
        y = cuda.threadIdx.y
        kmax = out.shape[1]
        for k in range(kmax):  # every row starts at zero (padding rows stay so)
            for kk in range(nv):
                c = t + kk * nt
                if c < m1:
                    out[b, k, c] = float32(0.0)
        n = ev_n[b]
        if n <= 0:
            return
        n_tab = table.shape[0]
        dt = par[1]
        eta = par[2]
        base_rel = par[3]
        log_eps = par[4]
        d_w = par[12]
        g_last = float32(g_n - 1)
        t0 = t0p[b]
        off = col_off[b]
        # This thread's entries s = t + kk·nt of [log, g_1 … g_M]: entry 0 is the
        # log (the row's constant, output column M), entry s ≥ 1 channel s − 1.
        xv = cuda.local.array(nv, float32)
        fv = cuda.local.array(nv, float32)
        fp = cuda.local.array(nv, float32)
        av = cuda.local.array(nv, float32)
        for kk in range(nv):
            s = t + kk * nt
            xv[kk] = x0[b, s - 1] if s >= 1 and s < m1 else float32(0.0)
            fv[kk] = float32(0.0)  # (0 · garbage could be NaN at grid point 0)
        # The last query's interval ends the walk.
        i_end, _ = grid_pos(t_us[b, n - 1], t0, dt, g_last)
        if n >= 2:
            i_r, _ = grid_pos(t_us[b, n - 2] + eta, t0, dt, g_last)
            i_end = max(i_end, i_r)
        # Stream heads: event ke at t_ke; release kr at t_{kr−1} + η (the first at 0).
        # A first reference before the recording (a carried one: t0 < 0) is read a
        # period later, as `_lowpass_rows` reads it (the band's schedule repeats);
        # out of the releases' time order, it is a head of its own (wrap).
        ke = 0
        kr = 0
        ie, fe = grid_pos(t_us[b, 0], t0, dt, g_last)
        wrap = t0 < float32(0.0)
        iw, fw = grid_pos(par[0], t0, dt, g_last)
        if wrap:
            kr = 1
            i_end = max(i_end, iw)
            ir, fr_ = grid_pos(t_us[b, 0] + eta, t0, dt, g_last)
        else:
            ir, fr_ = grid_pos(float32(0.0), t0, dt, g_last)
        # The filtered log, kept by every thread (entry 0's recursion, the same
        # operations): the decay's part of the Jacobian needs it at the point before.
        yl = float32(0.0)
        dtw = dt / d_w
        for j in range(0, i_end + 2):  # grid points 0 … i_end + 1
            i0, fr, inside = band_at(j, t0, off, par, n_tab)
            part = float32(0.0)
            for kk in range(nv):
                s = t + kk * nt
                a = float32(0.0)
                if inside and s >= 1 and s < m1:
                    a = table[i0, s - 1] * (float32(1.0) - fr) + table[i0 + 1, s - 1] * fr
                av[kk] = a
                part += a * xv[kk]
            inten = max(wsum(part, t, buf, y) + base_rel, float32(0.0))
            lev = inten + log_eps
            inv = float32(1.0) / lev
            lg = math.log(lev)
            alpha = float32(0.0)
            if j > 0:
                alpha = math.exp(-dt * inten / d_w)
            # the band's weight in the Jacobian: log's slope and the decay's part
            wg = (float32(1.0) - alpha) * inv - (yl - lg) * alpha * dtw
            for kk in range(nv):
                s = t + kk * nt
                fp[kk] = fv[kk]
                if s == 0:
                    fv[kk] = alpha * fv[kk] + (float32(1.0) - alpha) * lg
                else:
                    fv[kk] = alpha * fv[kk] + wg * av[kk]
            yl = alpha * yl + (float32(1.0) - alpha) * lg
            if j == 0:
                continue
            # Queries in the interval [j − 1, j] (or, were a stream out of order,
            # before it): events add the filtered state, releases subtract it.
            while ke < n and ie <= j - 1:
                for kk in range(nv):
                    s = t + kk * nt
                    if s < m1:
                        c = s - 1 if s >= 1 else m
                        out[b, ke, c] += fp[kk] * (float32(1.0) - fe) + fv[kk] * fe
                ke += 1
                if ke < n:
                    ie, fe = grid_pos(t_us[b, ke], t0, dt, g_last)
            while kr < n and ir <= j - 1:
                for kk in range(nv):
                    s = t + kk * nt
                    if s < m1:
                        c = s - 1 if s >= 1 else m
                        out[b, kr, c] -= fp[kk] * (float32(1.0) - fr_) + fv[kk] * fr_
                kr += 1
                if kr < n:
                    ir, fr_ = grid_pos(t_us[b, kr - 1] + eta, t0, dt, g_last)
            if wrap and iw <= j - 1:  # row 0's carried reference
                for kk in range(nv):
                    s = t + kk * nt
                    if s < m1:
                        c = s - 1 if s >= 1 else m
                        out[b, 0, c] -= fp[kk] * (float32(1.0) - fw) + fv[kk] * fw
                wrap = False
        # Each row: its constant, then the event's weight.
        for k in range(n):
            part = float32(0.0)
            for kk in range(nv):
                s = t + kk * nt
                if s >= 1 and s < m1:
                    part += out[b, k, s - 1] * xv[kk]
            dot = wsum(part, t, buf, y)
            w = w_log[b, k]
            p = pol[b, k]
            step = (thr_on[b] if p > 0 else thr_off[b]) * float32(p)
            for kk in range(nv):
                s = t + kk * nt
                if s == 0:
                    out[b, k, m] = (out[b, k, m] - dot - step) * w
                elif s < m1:
                    out[b, k, s - 1] *= w

    return kernel


def lowpass_params(rig, table, noise, sweeps: int) -> tuple[np.ndarray, int]:
    """The kernel's float32 parameters `par` (N_PAR) and grid length `g_n` for a rig,
    its channel table, noise model `[σ_C, σ_t, d_w]` and number of sweeps: the
    values `_problem._lowpass_rows` and `pixel_system`'s `a_at` compute with, in the
    rig's float32."""
    f = np.float32
    period = f(np.asarray(rig.period_us))
    n = int(rig.samples_per_sweep)
    mid = 0.5 * (rig.grid.start_nm + rig.grid.stop_nm)
    half = 0.5 * (rig.grid.stop_nm - rig.grid.start_nm)
    par = np.array(
        [period, period / f(n), np.asarray(rig.refractory_us),
         np.asarray(rig.baseline_rel), np.asarray(rig.log_eps),
         np.asarray(rig.sweep_start_nm), np.asarray(rig.band_speed_nm_per_us),
         np.asarray(rig.sweep_curvature_nm), mid, half, table.lo_nm, table.step_nm,
         max(float(np.asarray(noise)[2]), 1e-6)],
        np.float32,
    )  # fmt: skip
    assert par.size == N_PAR
    return par, sweeps * n + 1


_PARS: dict = {}


def _par_on_device(par: np.ndarray):
    """`par` on the device once per value (a host array would be copied over at
    every launch, synchronously)."""
    if simulated():
        return par
    key = par.tobytes()
    if key not in _PARS:
        _PARS[key] = cuda.to_device(par)
    return _PARS[key]


def lowpass_rows(px, ev_n, w_log, x0, table_values, par, g_n: int):
    """The photoreceptor model's event rows of a batch of pixels, linearised at `x0`
    `(B, M)`: `(B, K, M+1)` float32, as `pixel_system(..., x0=x0, return_rows=True)
    .events` (zero past each pixel's `ev_n` events). `px` is the batch's
    :class:`._problem.PixelEvents` (float32, on the GPU), `w_log` `(B, K)` the rows'
    weights (`PixelRows.log_weight`), `table_values` the channel table `(R, M)`,
    `par`, `g_n` from :func:`lowpass_params`. Returns a numba device array (a host
    array under the simulator), written by a kernel on numba's default stream: a
    launch after it on that stream sees it; anything else waits for the stream
    (`_cuda_kernel.synchronize`). The JAX inputs must be ready."""
    b, k = px.t_us.shape
    m = x0.shape[1]
    if simulated():
        nt, ppb = SIM_THREADS, 1
        out = np.zeros((b, k, m + 1), np.float32)
    else:
        nt, ppb = THREADS, PIXELS_PER_BLOCK
        out = cuda.device_array((b, k, m + 1), np.float32)
    kern = make_lowpass_kernel(m, nt, ppb)
    kern[-(-b // ppb), (nt, ppb)](
        as_cuda(px.t_us), as_cuda(px.polarity), as_cuda(ev_n),
        as_cuda(px.threshold_on), as_cuda(px.threshold_off), as_cuda(px.t0_phase_us),
        as_cuda(px.column_offset_us), as_cuda(x0), as_cuda(w_log),
        as_cuda(table_values), _par_on_device(par), np.int32(g_n), out,
    )  # fmt: skip
    return out
