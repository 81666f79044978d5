"""numba kernel of the fused CPU path (:mod:`._fused`): one pixel at a time, its rows
are formed as band segments, its Q accumulated in float64 inside the rows' envelope,
factorised by an envelope Cholesky and solved by the primal active-set method — the
same problem and the same steps as :func:`._problem.pixel_system` (ideal sensor) and
:func:`._solvers.active_set_batch`, without any M×M matrix leaving the cache.

Imported on first use (numba). Marked `no_type_check` so the jaxtyping import hook of
the test suite leaves it to numba.
"""

from __future__ import annotations

import math
from typing import no_type_check

import numpy as np

from .._base import njit

# Indices into the kernel's `par` (float64) and `ipar` (int64) vectors (see _fused.py).
P_BASE, P_ETA, P_PERIOD, P_SPEED, P_START, P_CURV, P_MID, P_HALF = range(8)
P_ARRIVE, P_LEAVE, P_TAU0, P_AINT, P_ASPEC, P_RIDGE, P_PEAK, P_TOL = range(8, 16)
P_SPEC_TRACE, P_TAB_LO, P_INV_STEP = range(16, 19)
I_SWEEPS, I_POINTS, I_TARGET, I_NORM, I_RELEASE, I_ITERS = range(6)


@njit(inline=True)
@no_type_check
def _u(i):
    """An index as unsigned: numba then drops its negative-index wraparound, and LLVM
    vectorises the loop with contiguous loads instead of gathers and scatters."""
    return np.uint64(i)


@njit(inline=True)
@no_type_check
def _band_at(t, phase, off, par, ntab):
    """Table row and fraction of the band at time `t` (order-1 lookup); row -1 when
    the band centre lies outside the table (zero response)."""
    period = par[P_PERIOD]
    local = t + phase
    local = local - period * math.floor(local / period)
    lin = par[P_START] + par[P_SPEED] * (local + off)
    u = (lin - par[P_MID]) / par[P_HALF]
    centre = lin + par[P_CURV] * (1.0 - u * u)
    pos = (centre - par[P_TAB_LO]) * par[P_INV_STEP]
    if pos < 0.0 or pos > ntab - 1:
        return -1, 0.0
    i0 = min(math.floor(pos), ntab - 2)
    return np.int64(i0), pos - i0


@njit(inline=True)
@no_type_check
def _add_band(row, coef, i0, frac, table, span_lo, span_hi, lohi):
    """row += coef · A(λc) over the band's span; widens `lohi` to cover it."""
    if i0 < 0 or coef == 0.0:
        return
    lo = min(span_lo[i0], span_lo[i0 + 1])
    hi = max(span_hi[i0], span_hi[i0 + 1])
    if lo >= hi:
        return
    c0 = coef * (1.0 - frac)
    c1 = coef * frac
    t0 = table[i0]
    t1 = table[i0 + 1]
    for m in range(_u(lo), _u(hi)):
        row[m] += c0 * t0[m] + c1 * t1[m]
    lohi[0] = min(lohi[0], lo)
    lohi[1] = max(lohi[1], hi)


@njit(inline=True)
@no_type_check
def _band_sum(i0, frac, tabsum):
    if i0 < 0:
        return 0.0
    return tabsum[i0] * (1.0 - frac) + tabsum[i0 + 1] * frac


@njit(inline=True)
@no_type_check
def _accumulate(row, c, lohi, qm, qv, first):
    """Q += r rᵀ (lower triangle), q += r c over the row's span; clears the row."""
    lo, hi = lohi[0], lohi[1]
    for i in range(lo, hi):
        ri = row[i]
        qi = qm[i]
        for j in range(_u(lo), _u(i + 1)):
            qi[j] += ri * row[j]
        qv[i] += ri * c
        if lo < first[i]:
            first[i] = lo
    for i in range(_u(lo), _u(hi)):
        row[i] = 0.0
    lohi[0] = row.size
    lohi[1] = 0


@njit(inline=True)
@no_type_check
def _dot1(a, ia, v, k0, k1):
    """Σ_{k0 ≤ k < k1} a[ia, k] v[k], four partial sums."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    r = a[ia]
    n4 = (k1 - k0) // 4
    for q in range(_u(n4)):
        k = _u(k0) + _u(4) * q
        s0 += r[k] * v[k]
        s1 += r[k + _u(1)] * v[k + _u(1)]
        s2 += r[k + _u(2)] * v[k + _u(2)]
        s3 += r[k + _u(3)] * v[k + _u(3)]
    for k in range(_u(k0 + 4 * n4), _u(k1)):
        s0 += r[k] * v[k]
    return (s0 + s1) + (s2 + s3)


@njit(inline=True)
@no_type_check
def _factor(qm, first, free, lf, inv):
    """Envelope Cholesky of Q restricted to the free variables (identity rows for the
    fixed ones): L's off-diagonal into `lf` (inside the envelope), the reciprocals of
    its diagonal into `inv` (products instead of divisions); False when a pivot is not
    positive. Row by row (left-looking): each entry is one dot product of two
    contiguous row pieces; consecutive dot products are independent, so the CPU
    overlaps them (a right-looking variant with vectorised rank-1 updates measured
    no faster: the envelope's rows are short)."""
    m = qm.shape[0]
    for i in range(m):
        fi = first[i]
        li = lf[i]
        qi = qm[i]
        if not free[i]:
            for j in range(_u(fi), _u(i)):
                li[j] = 0.0
            inv[i] = 1.0
            continue
        d = qi[i]
        for j in range(fi, i):
            if free[j]:
                lj = lf[j]
                s = qi[j]
                for k in range(_u(max(fi, first[j])), _u(j)):
                    s -= li[k] * lj[k]
                v = s * inv[j]
                li[j] = v
                d -= v * v
            else:
                li[j] = 0.0
        if not d > 0.0:
            return False
        inv[i] = 1.0 / math.sqrt(d)
    return True


@njit(inline=True)
@no_type_check
def _solve(lf, inv, first, free, qv, out):
    """out = -Q_free⁻¹ q on the free variables, 0 on the fixed ones."""
    m = qv.size
    for i in range(m):
        s = -qv[i] if free[i] else 0.0
        out[i] = (s - _dot1(lf, i, out, first[i], i)) * inv[i]
    for i in range(m - 1, -1, -1):
        xi = out[i] * inv[i]
        out[i] = xi
        li = lf[i]
        for k in range(_u(first[i]), _u(i)):
            out[k] -= li[k] * xi
    for i in range(m):
        if not free[i]:
            out[i] = 0.0


@njit(inline=True)
@no_type_check
def _gradient(qm, first, qv, x, g):
    """g = Q x + q with Q's lower triangle inside the envelope."""
    m = qv.size
    for i in range(m):
        g[i] = qv[i] + qm[i, i] * x[i]
    for i in range(m):
        xi = x[i]
        qi = qm[i]
        gi = 0.0
        for j in range(_u(first[i]), _u(i)):
            gi += qi[j] * x[j]
            g[j] += qi[j] * xi
        g[i] += gi


@njit
@no_type_check
def solve_pixels(
    sel, starts, use, t_sorted, s_sorted, lead, col_off, width, thr_on, thr_off,
    table, tabsum, span_lo, span_hi, spec, spec_first, par, ipar, out_x, out_kkt,
    out_steps,
):  # fmt: skip
    """Assemble and solve the pixels `sel` (flat indices); their events are
    `t_sorted[starts[p] : starts[p] + use[p]]` (µs from the recording start, time
    order) with polarities `s_sorted`. Writes each pixel's x, KKT residual and
    active-set steps (-1: a factorisation failed, x is NaN)."""
    m = table.shape[1]
    ntab = table.shape[0]
    base = par[P_BASE]
    log_base = math.log(base)
    eta = par[P_ETA]
    period = par[P_PERIOD]
    sweeps = ipar[I_SWEEPS]
    g = ipar[I_POINTS]
    target = ipar[I_TARGET]  # 0 linear, 1 peak, 2 flat, 3 flat-peak
    norm = ipar[I_NORM] != 0
    release = ipar[I_RELEASE] != 0
    max_iters = ipar[I_ITERS]
    peak = target == 1 or target == 3
    flat = target >= 2
    kmax = 1
    for r in range(sel.size):
        kmax = max(kmax, use[sel[r]])
    tt = np.empty(kmax)
    step = np.empty(kmax)
    sgn = np.empty(kmax)
    thr = np.empty(kmax)
    sweep_of = np.empty(kmax, np.int64)
    drift = np.empty(kmax)
    i_hat = np.empty(kmax)
    qm = np.zeros((m, m))
    lf = np.zeros((m, m))
    inv = np.zeros(m)
    qv = np.zeros(m)
    row = np.zeros(m)
    first = np.zeros(m, np.int64)
    free = np.ones(m, np.bool_)
    x = np.zeros(m)
    p = np.zeros(m)
    gr = np.zeros(m)
    lohi = np.zeros(2, np.int64)
    for r in range(sel.size):
        pix = sel[r]
        k = use[pix]
        s0 = starts[pix]
        d = lead[pix]
        phase = -d
        off = col_off[pix % width]
        t_on, t_off = thr_on[pix], thr_off[pix]
        qm[:, :] = 0.0
        qv[:] = 0.0
        for i in range(m):
            first[i] = i
        lohi[0] = m
        lohi[1] = 0
        # Events: steps, sweeps, drift on monotone flanks, level estimates.
        prev_s = 0.0
        level = 0.0
        peak_i = base
        for i in range(k):
            tt[i] = t_sorted[s0 + i] + d
            sg = 1.0 if s_sorted[s0 + i] > 0 else -1.0
            sgn[i] = sg
            thr[i] = t_on if sg > 0 else t_off
            step[i] = sg * thr[i]
            sweep_of[i] = np.int64(math.floor((tt[i] + phase) / period))
            new = i == 0 or sweep_of[i] != sweep_of[i - 1]
            t_ref = 0.0 if i == 0 else tt[i - 1] + eta
            gap = max(tt[i] - t_ref, 1.0)
            dr = 0.0
            if release and not new and prev_s == sg:
                dr = step[i] * min(eta / gap, 3.0)
            drift[i] = dr
            if new:
                level = 0.0
            level += step[i] + dr
            i_hat[i] = math.exp(log_base + level)
            peak_i = max(peak_i, i_hat[i])
            prev_s = sg
        s_hat = max(peak_i - base, 1e-3 * base)
        # Event rows: [a(τ) - e^{σC} a(ρ); c'(1 - e^{σC})] / Î.
        for i in range(k):
            ratio = math.exp(step[i])
            w = 1.0 / i_hat[i] if norm else 1.0
            t_ref = 0.0 if i == 0 else tt[i - 1] + eta
            b0, f0 = _band_at(tt[i], phase, off, par, ntab)
            b1, f1 = _band_at(t_ref, phase, off, par, ntab)
            _add_band(row, w, b0, f0, table, span_lo, span_hi, lohi)
            _add_band(row, -w * ratio, b1, f1, table, span_lo, span_hi, lohi)
            _accumulate(row, w * base * (1.0 - ratio), lohi, qm, qv, first)
        # Anti-drift rows over each sweep's lit interval.
        arrive = par[P_ARRIVE] - off
        leave = par[P_LEAVE] - off
        spacing = (leave - arrive) / g
        w_int0 = math.sqrt(par[P_AINT] * spacing / par[P_TAU0])
        nxt = 0
        for s in range(sweeps):
            t_arr = s * period - phase + arrive
            t_lv = s * period - phase + leave
            for j in range(g):
                t_g = t_arr + (j + 0.5) / g * (leave - arrive)
                while nxt < k and tt[nxt] <= t_g:
                    nxt += 1
                prv = nxt - 1
                b_ev = nxt < k and sweep_of[nxt] == s
                a_ev = prv >= 0 and tt[prv] + eta >= t_arr and sweep_of[prv] == s
                b_time = tt[nxt] if b_ev else t_lv
                a_time = tt[prv] + eta if a_ev else t_arr
                span = max(b_time - a_time, 1.0)
                sgf = min(max((t_g - a_time) / span, 0.0), 1.0)
                i_a = base
                if a_ev:
                    dn = drift[prv + 1] if prv + 1 < k else 0.0
                    i_a = i_hat[prv] * math.exp(dn)
                i_b = i_hat[nxt] if b_ev else base
                bump_h = 0.0
                if peak and a_ev and b_ev and sgn[prv] * sgn[nxt] < 0.0:
                    bump_h = sgn[prv] * math.expm1(par[P_PEAK] * thr[prv])
                bump = 4.0 * sgf * (1.0 - sgf) * bump_h
                bg, fg = _band_at(t_g, phase, off, par, ntab)
                ba, fa = -1, 0.0
                bb, fb = -1, 0.0
                if a_ev:
                    ba, fa = _band_at(tt[prv] + eta, phase, off, par, ntab)
                if b_ev:
                    bb, fb = _band_at(tt[nxt], phase, off, par, ntab)
                if flat:
                    f_g = _band_sum(bg, fg, tabsum)
                    f_a = max(_band_sum(ba, fa, tabsum), 1e-9)
                    f_b = max(_band_sum(bb, fb, tabsum), 1e-9)
                    wa = (1.0 - sgf if b_ev else 1.0) if a_ev else 0.0
                    wa += bump
                    wb = (sgf if a_ev else 1.0) if b_ev else 0.0
                    ca = wa * f_g / f_a if a_ev else 0.0
                    cb = wb * f_g / f_b if b_ev else 0.0
                    c_row = 0.0
                    i_tgt = base + f_g * (
                        wa * (i_a - base) / f_a + wb * (i_b - base) / f_b
                    )
                    i_tgt = max(i_tgt, base)
                else:
                    wa = 1.0 - sgf + bump
                    ca = wa if a_ev else 0.0
                    cb = sgf if b_ev else 0.0
                    c_row = -base * bump
                    i_tgt = max(wa * i_a + sgf * i_b, 1e-3 * base)
                w_int = w_int0 / i_tgt if norm else w_int0
                _add_band(row, w_int, bg, fg, table, span_lo, span_hi, lohi)
                _add_band(row, -w_int * ca, ba, fa, table, span_lo, span_hi, lohi)
                _add_band(row, -w_int * cb, bb, fb, table, span_lo, span_hi, lohi)
                if lohi[1] > lohi[0]:
                    _accumulate(row, w_int * c_row, lohi, qm, qv, first)
                else:
                    lohi[0] = m
                    lohi[1] = 0
        # Priors: α_spec/ŝ² S (its envelope) and the ridge.
        spec_w = par[P_ASPEC] / (s_hat * s_hat) if norm else par[P_ASPEC]
        trace = 0.0
        for i in range(m):
            trace += qm[i, i]
        ridge = par[P_RIDGE] * ((trace + spec_w * par[P_SPEC_TRACE]) / m + 1e-30)
        for i in range(m):
            for j in range(spec_first[i], i + 1):
                qm[i, j] += spec_w * spec[i, j]
            qm[i, i] += ridge
            if spec_first[i] < first[i]:
                first[i] = spec_first[i]
        # Box QP: the unconstrained minimiser, then active-set steps if needed.
        for i in range(m):
            free[i] = True
        steps = 0
        ok = _factor(qm, first, free, lf, inv)
        if ok:
            _solve(lf, inv, first, free, qv, x)
            neg = False
            for i in range(m):
                if x[i] < 0.0:
                    neg = True
                if x[i] <= 0.0:
                    x[i] = 0.0
                    free[i] = False
            done = not neg
            qmax = 0.0
            for i in range(m):
                qmax = max(qmax, abs(qm[i, i]))
            while not done and steps < max_iters:
                steps += 1
                if not _factor(qm, first, free, lf, inv):
                    ok = False
                    break
                _solve(lf, inv, first, free, qv, p)
                j_block = -1
                best = np.inf
                for i in range(m):
                    if free[i] and p[i] < 0.0:
                        ratio = x[i] / (x[i] - p[i])
                        if ratio < best:
                            best = ratio
                            j_block = i
                if j_block >= 0:  # blocked: move to the first bound, fix it
                    alpha = min(max(best, 0.0), 1.0)
                    for i in range(m):
                        x[i] = max(x[i] + alpha * (p[i] - x[i]), 0.0)
                    x[j_block] = 0.0
                    free[j_block] = False
                    continue
                _gradient(qm, first, qv, p, gr)
                pmax = 1e-30
                for i in range(m):
                    pmax = max(pmax, abs(p[i]))
                lim = -par[P_TOL] * qmax * pmax
                j_rel = -1
                best = np.inf
                for i in range(m):
                    if not free[i] and gr[i] < lim and gr[i] < best:
                        best = gr[i]
                        j_rel = i
                for i in range(m):
                    x[i] = p[i]
                if j_rel >= 0:
                    free[j_rel] = True
                else:
                    done = True
        if not ok:
            for i in range(m):
                out_x[r, i] = np.nan
            out_kkt[r] = np.nan
            out_steps[r] = -1
            continue
        _gradient(qm, first, qv, x, gr)
        qmax = 0.0
        for i in range(m):
            qmax = max(qmax, abs(qm[i, i]))
        kkt = 0.0
        for i in range(m):
            kkt = max(kkt, abs(x[i] - max(x[i] - gr[i] / qmax, 0.0)))
            out_x[r, i] = x[i]
        out_kkt[r] = kkt
        out_steps[r] = steps
