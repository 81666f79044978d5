"""numba kernel of the fused CPU path (:mod:`._fused`): one pixel at a time, its rows
are formed as band segments, its Q accumulated in float64 inside the rows' envelope,
factorised by an envelope Cholesky and solved by the primal active-set method — the
same problem and the same steps as :func:`._problem.pixel_system` (ideal or with a noise
model, including the photoreceptor pass and the robust reweighting of
:func:`._pipeline._solve_chunk`) and :func:`._solvers.active_set_batch`, without any
M×M matrix leaving the cache.

Pixels go in groups of four (`lanes=4`, the default), one per lane of a float64 × 4
vector register: each pixel's rows are formed on its own (band lookups, weights), then
the four pixels' Q are accumulated side by side in the *lane layout* (`_lane_rows`,
four rows per pass over Q), their priors added, and the four systems factorised and
solved together (`_solve_lanes`). The loops of both are short (a row's span, an
envelope row: ~16–21 entries), and their fixed cost — loop set-up, mispredicted exits —
is then paid once for four pixels. A pixel whose minimiser has a negative channel is
taken out of the lane layout for its active-set steps. Event rows whose reference
lies in the sweep before (blue against red: `LONG_SPAN`) are left out of the lanes'
Q and added after the factorisation by the Woodbury identity (`_lane_long_rows`).
With the noise model each pixel
of the group keeps its event rows and drift part, and the group is assembled and
solved together again after each photoreceptor pass and reweighting (a pixel whose
reweighting has converged sits out, its system rebuilt unchanged). The photoreceptor
pass itself runs the group's pixels side by side where they share a column offset
(`_lane_lowpass_rows`: each grid point's intensity, decay, logarithm and filter step
one four-lane operation; the same rows to the last bit as `_lowpass_rows`, which
serves the other groups and `lanes=1`). `lanes=1` keeps the
one-pixel path (`_accumulate`, `_assemble`, `_write_answer`), the reference the tests
compare the lanes with.

Imported on first use (numba). Marked `no_type_check` so the jaxtyping import hook of
the test suite leaves it to numba. The per-row helpers are inlined; `_assemble`
(called up to three times per pixel), `_box_qp`, `_lowpass_rows` and the lane
functions are compiled as functions of their own: inlining them too was no faster on
two threads in a development check and doubled the first compilation (~55 s against
~27 s, once per install: numba caches it).
"""

from __future__ import annotations

import functools
import math
from typing import no_type_check

import numpy as np

from .._base import njit as _njit
from .._model import BAND_TRIM

#: Every function of the kernel divides as NumPy does (`error_model="numpy"`: a
#: division by zero gives inf or NaN, which the factorisation's pivot tests and the
#: answers' finiteness checks catch, instead of raising): numba's default tests each
#: divisor, and that branch kept LLVM from vectorising the loops that divide.
njit = functools.partial(_njit, error_model="numpy")

# Indices into the kernel's `par` (float64) and `ipar` (int64) vectors (see _fused.py).
P_BASE, P_ETA, P_PERIOD, P_SPEED, P_START, P_CURV, P_MID, P_HALF = range(8)
P_ARRIVE, P_LEAVE, P_TAU0, P_AINT, P_ASPEC, P_RIDGE, P_PEAK, P_TOL = range(8, 16)
P_SPEC_TRACE, P_TAB_LO, P_INV_STEP = range(16, 19)
P_SIG_C, P_SIG_T, P_DW, P_FLOOR, P_ADARK, P_RC, P_REJECT = range(19, 26)
P_BASE_REL, P_LOG_EPS, P_LP_TOL, P_INV_PERIOD, P_INV_HALF = range(26, 31)
N_PAR = 31
I_SWEEPS, I_POINTS, I_TARGET, I_NORM, I_RELEASE, I_ITERS, I_NOISE, I_ROBUST = range(8)
I_LOWPASS, I_SAMPLES, I_LANES, I_LONG = range(8, 12)
#: A row's entries below this fraction of its largest count as zero: each band of the
#: table (`BandTable.trimmed`: the channels a band centre lights, `_fused.
#: FusedProblem`'s `span_lo`, `span_hi`) and each row of the photoreceptor pass
#: (`_lowpass_finish`). 1e-7 is about one float32 ulp of the row's peak; on the
#: paper's rig it cuts a band's span from ~20 channels to ~16, and with it Q's
#: envelope (1.08× the ideal kernel). Answers move by ≤ 0.002° SAM against the
#: untrimmed problem; at 1e-6 (1.11×) two pixels of the narrow-peak test scene, whose
#: floors are near-degenerate, moved by 0.27° (Performance log, "Eighteenth session").
TRIM = BAND_TRIM
#: Pixels whose factorisations run side by side, one per SIMD lane (float64 × 4:
#: AVX2). The lane code is written out for four lanes.
LANES = 4


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
    local = local - period * math.floor(local * par[P_INV_PERIOD])
    return _band_local(local, off, par, ntab)


@njit(inline=True)
@no_type_check
def _band_local(local, off, par, ntab):
    """:func:`_band_at` at the local time `local` within the sweep (in [0, period))."""
    lin = par[P_START] + par[P_SPEED] * (local + off)
    u = (lin - par[P_MID]) * par[P_INV_HALF]
    centre = lin + par[P_CURV] * (1.0 - u * u)
    pos = (centre - par[P_TAB_LO]) * par[P_INV_STEP]
    if pos < 0.0 or pos > ntab - 1:
        return -1, 0.0
    i0 = min(math.floor(pos), ntab - 2)
    return np.int64(i0), pos - i0


@njit(inline=True)
@no_type_check
def _add_bands(row, segs, table, span_lo, span_hi, lohi):
    """row += coef · A(λc) for each segment (table row i0, fraction, coef) of `segs`,
    over the band's span (rows outside the table or with coef 0 add nothing); widens
    `lohi` to cover them. One call per row, not per segment: each call of an inlined
    helper costs numba an atomic reference count increment and decrement per array
    argument (a sampling profile put ~15 % of the kernel's time in them when each
    segment was a call of its own)."""
    for seg in segs:
        i0 = seg[0]
        frac = seg[1]
        coef = seg[2]
        if i0 < 0 or coef == 0.0:
            continue
        lo = min(span_lo[i0], span_lo[i0 + 1])
        hi = max(span_hi[i0], span_hi[i0 + 1])
        if lo >= hi:
            continue
        c0 = coef * (1.0 - frac)
        c1 = coef * frac
        t0 = _u(i0)
        t1 = _u(i0 + 1)
        for m in range(_u(lo), _u(hi)):
            row[m] += c0 * table[t0, m] + c1 * table[t1, m]
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
def _acc_stored(qm, qv, first, r, c, lo, hi, s2):
    """Q += s2 r rᵀ (lower triangle), q += s2 r c over [lo, hi) (the row is kept)."""
    for i in range(lo, hi):
        ri = s2 * r[i]
        qi = qm[i]
        for j in range(_u(lo), _u(i + 1)):
            qi[j] += ri * r[j]
        qv[i] += ri * c
        if lo < first[i]:
            first[i] = lo


@njit(inline=True)
@no_type_check
def _accumulate(row, c, lohi, qm, qv, first):
    """Q += r rᵀ (lower triangle), q += r c over the row's span; clears the row."""
    lo, hi = lohi[0], lohi[1]
    _acc_stored(qm, qv, first, row, c, lo, hi, 1.0)
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


@njit(inline=True)
@no_type_check
def _add_events(qm, qv, first, evr, evc, evlo, evhi, u, k):
    """The kept event rows into Q and q, row i weighted by u[i] (a row's residual
    by u, its Gram term by u²; u = 0 drops it)."""
    for i in range(k):
        if evhi[i] > evlo[i] and u[i] > 0.0:
            _acc_stored(qm, qv, first, evr[i], evc[i], evlo[i], evhi[i], u[i] * u[i])


@njit(inline=True)
@no_type_check
def _clear_events(evr, evlo, evhi, k):
    """Zero the kept event rows (each only over its span)."""
    for i in range(k):
        ri = evr[i]
        for j in range(_u(evlo[i]), _u(evhi[i])):
            ri[j] = 0.0


@njit(inline=True)
@no_type_check
def _restore_drift(qm, qv, qd, qvd, first):
    """Q, q ← the kept drift part (anti-drift and dark-channel rows) over the
    envelope."""
    m = qv.size
    for i in range(m):
        qv[i] = qvd[i]
        qi = qm[i]
        di = qd[i]
        for j in range(_u(first[i]), _u(i + 1)):
            qi[j] = di[j]


@njit(inline=True)
@no_type_check
def _add_priors(qm, first, spec, spec_first, spec_w, ridge_rel, spec_trace):
    """The spectral prior spec_w·S (inside its envelope) and the ridge
    ridge_rel·(tr Q_data + spec_w tr S)/M, as :func:`._problem._system`."""
    m = qm.shape[0]
    trace = 0.0
    for i in range(m):
        trace += qm[i, i]
    ridge = ridge_rel * ((trace + spec_w * spec_trace) / m + 1e-30)
    for i in range(m):
        qi = qm[i]
        si = spec[i]
        for j in range(_u(spec_first[i]), _u(i + 1)):
            qi[j] += spec_w * si[j]
        qi[i] += ridge
        if spec_first[i] < first[i]:
            first[i] = spec_first[i]


@njit
@no_type_check
def _box_qp(qm, qv, first, free, lf, inv, x, p, gr, tol, max_iters, have_x):
    """min ½xᵀQx + qᵀx, x ≥ 0: the unconstrained minimiser (already in `x` when
    `have_x`), then the primal active-set steps of :func:`._solvers.active_set_step`
    where a bound is violated. Returns the steps taken, −1 when a factorisation
    failed."""
    m = qv.size
    for i in range(m):
        free[i] = True
    if not have_x:
        if not _factor(qm, first, free, lf, inv):
            return -1
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
    steps = 0
    while not done and steps < max_iters:
        steps += 1
        if not _factor(qm, first, free, lf, inv):
            return -1
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
        lim = -tol * qmax * pmax
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
    return steps


@njit(inline=True)
@no_type_check
def _lane_pivot(d, fail, lane):
    """1/√d for a lane's pivot d; a pivot that is not positive marks the lane failed
    and counts as 1 (its factorisation carries on, unused)."""
    if not d > 0.0:
        fail[lane] = True
        return 1.0
    return 1.0 / math.sqrt(d)


@njit(inline=True)
@no_type_check
def _lane_factor(ql, ptr, fu, lf, inv, fail, m):
    """:func:`_factor` of four systems at once, all free, in the lane layout of
    :func:`_solve_lanes`: lane l of entry (i, j) at `4 (ptr[i] - fu[i] + j) + l`.
    Per lane the operations of `_factor` (the union envelope only adds products with
    exact zeros), but each dot product in two partial sums (even and odd k): as one
    chain of dependent subtractions it was latency-bound (development check: 5 % of
    the kernel's time; four sums, or two rows of L at a time, gained nothing more).
    So the last bits differ from `_factor`'s. A lane whose pivot is not positive is
    marked in `fail` and carried on with pivot 1."""
    for i in range(m):
        fi = fu[i]
        pi = ptr[i] - fi
        e = _u(4 * (pi + i))
        d0 = ql[e]
        d1 = ql[e + _u(1)]
        d2 = ql[e + _u(2)]
        d3 = ql[e + _u(3)]
        for j in range(fi, i):
            pj = ptr[j] - fu[j]
            e = _u(4 * (pi + j))
            s0 = ql[e]
            s1 = ql[e + _u(1)]
            s2 = ql[e + _u(2)]
            s3 = ql[e + _u(3)]
            k0 = max(fi, fu[j])
            n2 = (j - k0) // 2
            t0 = t1 = t2 = t3 = 0.0
            for q in range(_u(n2)):
                k = _u(k0) + _u(2) * q
                a = _u(4) * (_u(pi) + k)
                b = _u(4) * (_u(pj) + k)
                s0 -= lf[a] * lf[b]
                s1 -= lf[a + _u(1)] * lf[b + _u(1)]
                s2 -= lf[a + _u(2)] * lf[b + _u(2)]
                s3 -= lf[a + _u(3)] * lf[b + _u(3)]
                t0 -= lf[a + _u(4)] * lf[b + _u(4)]
                t1 -= lf[a + _u(5)] * lf[b + _u(5)]
                t2 -= lf[a + _u(6)] * lf[b + _u(6)]
                t3 -= lf[a + _u(7)] * lf[b + _u(7)]
            if k0 + 2 * n2 < j:
                a = _u(4 * (pi + j - 1))
                b = _u(4 * (pj + j - 1))
                s0 -= lf[a] * lf[b]
                s1 -= lf[a + _u(1)] * lf[b + _u(1)]
                s2 -= lf[a + _u(2)] * lf[b + _u(2)]
                s3 -= lf[a + _u(3)] * lf[b + _u(3)]
            s0 += t0
            s1 += t1
            s2 += t2
            s3 += t3
            c = _u(4 * j)
            v0 = s0 * inv[c]
            v1 = s1 * inv[c + _u(1)]
            v2 = s2 * inv[c + _u(2)]
            v3 = s3 * inv[c + _u(3)]
            lf[e] = v0
            lf[e + _u(1)] = v1
            lf[e + _u(2)] = v2
            lf[e + _u(3)] = v3
            d0 -= v0 * v0
            d1 -= v1 * v1
            d2 -= v2 * v2
            d3 -= v3 * v3
        c = _u(4 * i)
        inv[c] = _lane_pivot(d0, fail, 0)
        inv[c + _u(1)] = _lane_pivot(d1, fail, 1)
        inv[c + _u(2)] = _lane_pivot(d2, fail, 2)
        inv[c + _u(3)] = _lane_pivot(d3, fail, 3)


@njit(inline=True)
@no_type_check
def _lane_solve(lf, ptr, fu, inv, qv, out, m):
    """:func:`_solve` (all free) of the four factorised systems: out = -Q⁻¹ q per
    lane, `qv` and `out` as (i, lane) at 4 i + lane. The forward dot products in four
    partial sums per lane, like `_dot1`'s but grouped from the union envelope's start
    (so the last bits differ from the one-pixel solve); one sum per lane was ~3 %
    slower in a development check."""
    for i in range(m):
        pi = ptr[i] - fu[i]
        a0 = a1 = a2 = a3 = 0.0
        b0 = b1 = b2 = b3 = 0.0
        c0 = c1 = c2 = c3 = 0.0
        e0 = e1 = e2 = e3 = 0.0
        k0 = fu[i]
        n4 = (i - k0) // 4
        for q in range(_u(n4)):
            k = _u(k0) + _u(4) * q
            a = _u(4) * (_u(pi) + k)
            o = _u(4) * k
            a0 += lf[a] * out[o]
            a1 += lf[a + _u(1)] * out[o + _u(1)]
            a2 += lf[a + _u(2)] * out[o + _u(2)]
            a3 += lf[a + _u(3)] * out[o + _u(3)]
            b0 += lf[a + _u(4)] * out[o + _u(4)]
            b1 += lf[a + _u(5)] * out[o + _u(5)]
            b2 += lf[a + _u(6)] * out[o + _u(6)]
            b3 += lf[a + _u(7)] * out[o + _u(7)]
            c0 += lf[a + _u(8)] * out[o + _u(8)]
            c1 += lf[a + _u(9)] * out[o + _u(9)]
            c2 += lf[a + _u(10)] * out[o + _u(10)]
            c3 += lf[a + _u(11)] * out[o + _u(11)]
            e0 += lf[a + _u(12)] * out[o + _u(12)]
            e1 += lf[a + _u(13)] * out[o + _u(13)]
            e2 += lf[a + _u(14)] * out[o + _u(14)]
            e3 += lf[a + _u(15)] * out[o + _u(15)]
        for k in range(_u(k0 + 4 * n4), _u(i)):
            a = _u(4) * (_u(pi) + k)
            o = _u(4) * k
            a0 += lf[a] * out[o]
            a1 += lf[a + _u(1)] * out[o + _u(1)]
            a2 += lf[a + _u(2)] * out[o + _u(2)]
            a3 += lf[a + _u(3)] * out[o + _u(3)]
        c = _u(4 * i)
        out[c] = (-qv[c] - ((a0 + b0) + (c0 + e0))) * inv[c]
        out[c + _u(1)] = (-qv[c + _u(1)] - ((a1 + b1) + (c1 + e1))) * inv[c + _u(1)]
        out[c + _u(2)] = (-qv[c + _u(2)] - ((a2 + b2) + (c2 + e2))) * inv[c + _u(2)]
        out[c + _u(3)] = (-qv[c + _u(3)] - ((a3 + b3) + (c3 + e3))) * inv[c + _u(3)]
    for i in range(m - 1, -1, -1):
        c = _u(4 * i)
        x0 = out[c] * inv[c]
        x1 = out[c + _u(1)] * inv[c + _u(1)]
        x2 = out[c + _u(2)] * inv[c + _u(2)]
        x3 = out[c + _u(3)] * inv[c + _u(3)]
        out[c] = x0
        out[c + _u(1)] = x1
        out[c + _u(2)] = x2
        out[c + _u(3)] = x3
        pi = ptr[i] - fu[i]
        for k in range(_u(fu[i]), _u(i)):
            _lane_update(out, _u(4) * k, lf, _u(4) * (_u(pi) + k), -x0, -x1, -x2, -x3)


# The lane layout: four pixels' systems side by side, lane l of entry (i, j) of an
# M×M matrix at 4 (i M + j) + l, of a vector's entry i at 4 i + l; each pixel's part
# is zero outside the group's union envelope `fu` (the first column in use in each
# row, the smallest over the four). Lanes ≥ nl repeat lane nl − 1 (their answers are
# not used). The functions on it are compiled with numba's SLP vectoriser
# (`njit(slp=True)`): without it the four lanes' operations stay scalar.


@njit(inline=True)
@no_type_check
def _lane_add(dst, d, s0, s1, s2, s3, a0, a1, a2, a3):
    """dst[d + l] += a_l s_l for the four lanes l, every load before the first store:
    with a store between the loads LLVM's SLP vectoriser leaves the four lanes
    scalar (it did in the lane solves' remainder loops, which run most of the time
    for rows this short), as `dst` and a source array may be the same as far as it
    knows."""
    v0 = dst[d]
    v1 = dst[d + _u(1)]
    v2 = dst[d + _u(2)]
    v3 = dst[d + _u(3)]
    dst[d] = v0 + a0 * s0
    dst[d + _u(1)] = v1 + a1 * s1
    dst[d + _u(2)] = v2 + a2 * s2
    dst[d + _u(3)] = v3 + a3 * s3


@njit(inline=True)
@no_type_check
def _lane_update(dst, d, src, s, a0, a1, a2, a3):
    """dst[d + l] += a_l src[s + l] for the four lanes l (:func:`_lane_add`)."""
    _lane_add(
        dst, d, src[s], src[s + _u(1)], src[s + _u(2)], src[s + _u(3)], a0, a1, a2, a3
    )  # fmt: skip


@njit(inline=True)
@no_type_check
def _lane_index(nl):
    """The pixel each of the four lanes carries (the last one repeated)."""
    top = nl - 1
    return 0, min(1, top), min(2, top), min(3, top)


@njit(slp=True)
@no_type_check
def _lane_clear(ql, qvl, qdl, qvdl, keep, fu, m):
    """Zero Q and q (and the kept drift part, if `keep`) over the envelope `fu` of the
    previous group; reset the envelope to the diagonal."""
    for i in range(m):
        for j in range(_u(4 * (i * m + fu[i])), _u(4 * (i * m + i + 1))):
            ql[j] = 0.0
        for j in range(_u(4 * i), _u(4 * i + 4)):
            qvl[j] = 0.0
        if keep:
            for j in range(_u(4 * (i * m + fu[i])), _u(4 * (i * m + i + 1))):
                qdl[j] = 0.0
            for j in range(_u(4 * i), _u(4 * i + 4)):
                qvdl[j] = 0.0
        fu[i] = i


@njit(slp=True)
@no_type_check
def _lane_copy(src, srcv, dst, dstv, fu, m):
    """dst, dstv ← src, srcv over the envelope `fu` (keeping or restoring the drift
    part)."""
    for i in range(m):
        for j in range(_u(4 * (i * m + fu[i])), _u(4 * (i * m + i + 1))):
            dst[j] = src[j]
        for j in range(_u(4 * i), _u(4 * i + 4)):
            dstv[j] = srcv[j]


@njit(inline=True)
@no_type_check
def _lane_axpy(q0, q1, q2, q3, src, s, a0, a1, a2, a3):
    """(q_l + a_l src[s + l]) for the four lanes l."""
    return (
        q0 + a0 * src[s], q1 + a1 * src[s + _u(1)], q2 + a2 * src[s + _u(2)],
        q3 + a3 * src[s + _u(3)],
    )  # fmt: skip


@njit(inline=True)
@no_type_check
def _lane_coefs(sw, r, rl, e):
    """The four lanes' w² r_i of row r of a chunk (`_lane_rows`)."""
    k = _u(4 * r)
    return (
        sw[k] * rl[e], sw[k + _u(1)] * rl[e + _u(1)], sw[k + _u(2)] * rl[e + _u(2)],
        sw[k + _u(3)] * rl[e + _u(3)],
    )  # fmt: skip


#: Rows added to Q per pass over it in `_lane_rows`.
ROWS_PER_PASS = 4

#: An event row whose reference lies in the sweep before — a sweep's first event
#: against the previous sweep's last one (a carried reference on the per-sweep path,
#: every sweep boundary of a whole-file reconstruction) — and which spans more than
#: this many channels (a band segment spans ~16) is *long*: its two band segments
#: lie at the spectrum's two ends (blue against red). Added into Q it widens Q's
#: envelope from its first column down every row it reaches: on the second sweep of
#: a 96×144 ColorChecker from 22.3 to 35.5 columns per row on average, 2.8× the
#: factorisation's multiply-adds. So the lanes leave up to `LONG_ROWS` long rows per
#: pixel out of Q (B = Q − Σ s r rᵀ) and add them after the factorisation by the
#: Woodbury identity (:func:`_lane_long_rows`). Rows within a sweep are never held
#: out, however wide: a gap between two events is also spanned by the anti-drift
#: rows in it, so Q's envelope stays as wide (holding out event rows wider than 40
#: channels on a single sweep cost 0.92× in a development check). Not with the
#: photoreceptor rows, which are wide by nature (the filter remembers every channel
#: the band has lit).
LONG_SPAN = 40
LONG_ROWS = 4


@njit(slp=True)
@no_type_check
def _lane_rows(rows, los, his, cs, ws, counts, nl, nrows, rl, sw, st, ql, qvl, fu, m):
    """Q += w² r rᵀ (lower triangle), q += w² r c for the rows j < nrows of the
    group's pixels, four side by side: row j of pixel l is `rows[l, j]`, zero outside
    `[los[l, j], his[l, j])`, with weight `ws[l, j]` and constant `cs[l, j]`; a pixel
    has no row j ≥ `counts[l]` (its row buffer is zero there).

    Four rows of the four pixels at a time (one load and store of Q for four rows:
    the loops are short, and their overhead is most of the cost), each entry updated
    row after row: per lane the same operations in the same order as
    :func:`_acc_stored`, plus products with exact zeros, so each pixel's Q is the
    one-pixel kernel's. Row i of Q is updated from the first column of the chunk's
    rows that reach i, not from the first column of their union: with the union, one
    long row of one pixel had widened the group's envelope (and so the
    factorisation's work) over the whole chunk — 2.2× the factorisation's
    multiply-adds on the ideal ColorChecker. `rl` (16 M), `sw` (32) and `st`
    (M + 32, int) are work space: the chunk's rows interleaved by lane, their w² and
    constants, the first column per row of Q and the rows' spans in order."""
    l0, l1, l2, l3 = _lane_index(nl)
    m4 = _u(4 * m)
    slo = st[m:]  # the chunk's row spans, ordered by their first column
    shi = st[m + 4 * ROWS_PER_PASS :]
    for j0 in range(0, nrows, ROWS_PER_PASS):
        ns = 0
        hi = 0
        for j in range(j0, min(j0 + ROWS_PER_PASS, nrows)):
            for lane in (l0, l1, l2, l3):
                if j < counts[lane] and his[lane, j] > los[lane, j]:
                    a = los[lane, j]
                    b = his[lane, j]
                    hi = max(hi, b)
                    q = ns
                    while q > 0 and slo[q - 1] > a:
                        slo[q] = slo[q - 1]
                        shi[q] = shi[q - 1]
                        q -= 1
                    slo[q] = a
                    shi[q] = b
                    ns += 1
        if ns == 0:
            continue
        lo = slo[0]
        # Row i of Q gets entries from column st[i] on: the first column of the
        # chunk's rows that reach i (not of their union, which would widen Q's
        # envelope); i + 1 where none does.
        for i in range(lo, hi):
            st[i] = i + 1
        cov = lo
        for q in range(ns):
            a = slo[q]
            for i in range(max(a, cov), shi[q]):
                st[i] = a
            cov = max(cov, shi[q])
        for r in range(ROWS_PER_PASS):
            j = j0 + r
            o = _u(r) * m4
            if j >= nrows:
                for c in range(_u(4 * lo), _u(4 * hi)):
                    rl[o + c] = 0.0
                for lane in range(4):
                    sw[4 * r + lane] = 0.0
                    sw[16 + 4 * r + lane] = 0.0
                continue
            r0 = rows[l0, j]
            r1 = rows[l1, j]
            r2 = rows[l2, j]
            r3 = rows[l3, j]
            for c in range(_u(lo), _u(hi)):
                e = o + _u(4) * c
                rl[e] = r0[c]
                rl[e + _u(1)] = r1[c]
                rl[e + _u(2)] = r2[c]
                rl[e + _u(3)] = r3[c]
            for lane in range(4):
                src = (l0, l1, l2, l3)[lane]
                w = ws[src, j] if j < counts[src] else 0.0
                sw[4 * r + lane] = w * w
                sw[16 + 4 * r + lane] = cs[src, j] if w != 0.0 else 0.0
        for i in range(lo, hi):
            s0 = st[i]
            if s0 > i:
                continue
            e = _u(4 * i)
            a00, a01, a02, a03 = _lane_coefs(sw, 0, rl, e)
            a10, a11, a12, a13 = _lane_coefs(sw, 1, rl, e + m4)
            a20, a21, a22, a23 = _lane_coefs(sw, 2, rl, e + _u(2) * m4)
            a30, a31, a32, a33 = _lane_coefs(sw, 3, rl, e + _u(3) * m4)
            base = _u(4 * i * m)
            for jj in range(_u(s0), _u(i + 1)):
                f = base + _u(4) * jj
                g = _u(4) * jj
                q0 = ql[f]
                q1 = ql[f + _u(1)]
                q2 = ql[f + _u(2)]
                q3 = ql[f + _u(3)]
                q0, q1, q2, q3 = _lane_axpy(q0, q1, q2, q3, rl, g, a00, a01, a02, a03)
                q0, q1, q2, q3 = _lane_axpy(
                    q0, q1, q2, q3, rl, g + m4, a10, a11, a12, a13
                )  # fmt: skip
                q0, q1, q2, q3 = _lane_axpy(
                    q0, q1, q2, q3, rl, g + _u(2) * m4, a20, a21, a22, a23
                )  # fmt: skip
                q0, q1, q2, q3 = _lane_axpy(
                    q0, q1, q2, q3, rl, g + _u(3) * m4, a30, a31, a32, a33
                )  # fmt: skip
                ql[f] = q0
                ql[f + _u(1)] = q1
                ql[f + _u(2)] = q2
                ql[f + _u(3)] = q3
            v0 = qvl[e]
            v1 = qvl[e + _u(1)]
            v2 = qvl[e + _u(2)]
            v3 = qvl[e + _u(3)]
            v0, v1, v2, v3 = _lane_axpy(v0, v1, v2, v3, sw, _u(16), a00, a01, a02, a03)
            v0, v1, v2, v3 = _lane_axpy(v0, v1, v2, v3, sw, _u(20), a10, a11, a12, a13)
            v0, v1, v2, v3 = _lane_axpy(v0, v1, v2, v3, sw, _u(24), a20, a21, a22, a23)
            v0, v1, v2, v3 = _lane_axpy(v0, v1, v2, v3, sw, _u(28), a30, a31, a32, a33)
            qvl[e] = v0
            qvl[e + _u(1)] = v1
            qvl[e + _u(2)] = v2
            qvl[e + _u(3)] = v3
            if s0 < fu[i]:
                fu[i] = s0


@njit
@no_type_check
def _hold_long_rows(nl, evlos, evhis, evxs, zzs, g_k, lng, lzz):
    """Take the group's long event rows (those marked in `evxs`, their reference in
    the sweep before, spanning more than `LONG_SPAN` channels; at most `LONG_ROWS`
    per pixel) out of the next accumulation: their spans emptied and weights zeroed; per pixel q
    `lng[q, 0]` of them, row n's index `lng[q, 1 + n]`, its span's end
    `lng[q, 1 + LONG_ROWS + n]`, its weight `lzz[q, n]`. :func:`_restore_long_rows`
    undoes it."""
    for q in range(LANES):
        lng[q, 0] = 0
    for q in range(nl):
        n = 0
        for j in range(g_k[q]):
            if n < LONG_ROWS and evxs[q, j] and evhis[q, j] - evlos[q, j] > LONG_SPAN:
                lng[q, 1 + n] = j
                lng[q, 1 + LONG_ROWS + n] = evhis[q, j]
                lzz[q, n] = zzs[q, j]
                evhis[q, j] = evlos[q, j]
                zzs[q, j] = 0.0
                n += 1
        lng[q, 0] = n


@njit
@no_type_check
def _restore_long_rows(nl, evhis, zzs, lng, lzz, evrs, evcs, evlos, qvl):
    """The long rows' spans and weights back (:func:`_hold_long_rows`), and their
    part of q added to the lanes' `qvl` (their part of Q is :func:`_lane_long_rows`'
    business)."""
    for q in range(nl):
        for n in range(lng[q, 0]):
            evhis[q, lng[q, 1 + n]] = lng[q, 1 + LONG_ROWS + n]
            zzs[q, lng[q, 1 + n]] = lzz[q, n]
    lanes = _lane_index(nl)
    for lane in range(4):
        q = lanes[lane]
        for n in range(lng[q, 0]):
            j = lng[q, 1 + n]
            r = evrs[q, j]
            f = lzz[q, n] * lzz[q, n] * evcs[q, j]
            for i in range(evlos[q, j], lng[q, 1 + LONG_ROWS + n]):
                qvl[4 * i + lane] += f * r[i]


@njit(inline=True)
@no_type_check
def _lane_woodbury(q, lng, lzz, evrs, evlos, zl, v, hw, m):
    """v ← v − Z u∘w for pixel (lane) q, with (I + U RᵀZ U) w = u∘(Rᵀv): from
    v = −B⁻¹b to −Q⁻¹b for Q = B + R S Rᵀ (:func:`_lane_long_rows`; `zl` = −Z)."""
    nk = lng[q, 0]
    hm = hw[: LONG_ROWS * LONG_ROWS]
    rhs = hw[LONG_ROWS * LONG_ROWS : LONG_ROWS * LONG_ROWS + LONG_ROWS]
    y = hw[LONG_ROWS * LONG_ROWS + LONG_ROWS :]
    for k in range(nk):
        r = evrs[q, lng[q, 1 + k]]
        lo = evlos[q, lng[q, 1 + k]]
        hi = lng[q, 1 + LONG_ROWS + k]
        a = 0.0
        for i in range(lo, hi):
            a += r[i] * v[4 * i + q]
        rhs[k] = lzz[q, k] * a
        for k2 in range(nk):  # (r_k · z_k2)
            g = 0.0
            zk = zl[k2]
            for i in range(lo, hi):
                g -= r[i] * zk[4 * i + q]
            hm[k * LONG_ROWS + k2] = lzz[q, k] * g * lzz[q, k2]
    for k in range(nk):  # H = I + U G U, symmetrised; its Cholesky factor
        for k2 in range(k):
            hm[k * LONG_ROWS + k2] = 0.5 * (
                hm[k * LONG_ROWS + k2] + hm[k2 * LONG_ROWS + k]
            )  # fmt: skip
        hm[k * LONG_ROWS + k] += 1.0
    for k in range(nk):
        for k2 in range(k + 1):
            t = hm[k * LONG_ROWS + k2]
            for c in range(k2):
                t -= hm[k * LONG_ROWS + c] * hm[k2 * LONG_ROWS + c]
            if k2 == k:
                hm[k * LONG_ROWS + k] = math.sqrt(t)
            else:
                hm[k * LONG_ROWS + k2] = t / hm[k2 * LONG_ROWS + k2]
    for k in range(nk):  # forward, then backward substitution
        t = rhs[k]
        for c in range(k):
            t -= hm[k * LONG_ROWS + c] * y[c]
        y[k] = t / hm[k * LONG_ROWS + k]
    for k in range(nk - 1, -1, -1):
        t = y[k]
        for c in range(k + 1, nk):
            t -= hm[c * LONG_ROWS + k] * y[c]
        y[k] = t / hm[k * LONG_ROWS + k]
    for k in range(nk):
        yk = lzz[q, k] * y[k]
        zk = zl[k]
        for i in range(m):  # v − Z y, and zl holds −Z
            v[4 * i + q] += zk[4 * i + q] * yk


@njit(slp=True)
@no_type_check
def _lane_long_rows(nl, todo, fail, lng, lzz, evrs, evlos, ptr, fu, lf, inv, xl, lw, m):
    """The minimisers of Q = B + Σ_k s_k r_k r_kᵀ from those of B (`xl`, after
    :func:`_solve_lanes` factorised B, the lanes' Q, into `lf`, `inv`), for the
    pixels' long rows r_k (weights s_k = `lzz`²; :func:`_hold_long_rows`), by the
    Woodbury identity: Z = B⁻¹R (one lane solve per long row, the four lanes side by
    side), then per pixel x = x_B − Z u∘w with (I + U RᵀZ U) w = u∘(Rᵀx_B), U =
    diag(u), u_k = `lzz`: a K×K system, I plus a positive semidefinite matrix,
    solved by Cholesky (:func:`_lane_woodbury`). Pixels without long rows keep `xl`
    as it is. `lw` (LONG_ROWS + 2, 4M) is work space.

    The answers are the one-pixel kernel's to rounding, which B (worse conditioned
    than Q, as it lacks rows) amplifies on ill-conditioned pixels: on the second
    sweep of a 96×144 ColorChecker (per-sweep path) the largest change was 0.015°
    SAM, every KKT residual ≤ 4e-13 (development check). One step of iterative
    refinement (the residual Q x + q, corrected by the same identity) brought the
    residuals to 2e-15 without moving the answers nearer the one-pixel kernel's, at
    ~9 % of that sweep's time: not kept."""
    zl = lw[:LONG_ROWS]
    rv = lw[LONG_ROWS]
    hw = lw[LONG_ROWS + 1]
    kmax = 0
    for q in range(nl):
        if todo[q] and not fail[q]:
            kmax = max(kmax, lng[q, 0])
    if kmax == 0:
        return
    lanes = _lane_index(nl)
    for k in range(kmax):
        for c in range(_u(4 * m)):
            rv[c] = 0.0
        for lane in range(4):
            q = lanes[lane]
            if todo[q] and k < lng[q, 0]:
                r = evrs[q, lng[q, 1 + k]]
                for i in range(evlos[q, lng[q, 1 + k]], lng[q, 1 + LONG_ROWS + k]):
                    rv[4 * i + lane] = r[i]
        _lane_solve(lf, ptr, fu, inv, rv, zl[k], m)  # −B⁻¹ r_k
    for q in range(nl):
        if todo[q] and not fail[q] and lng[q, 0] > 0:
            _lane_woodbury(q, lng, lzz, evrs, evlos, zl, xl, hw, m)


@njit
@no_type_check
def _add_long_rows(qm, qv, first, q, lng, lzz, evrs, evlos):
    """Pixel `q`'s long rows into its own Q (:func:`_acc_stored`; its q holds them
    already, :func:`_lane_assemble`, so they add 0 · r to it), when it leaves the
    lanes for the active set with its whole system."""
    for n in range(lng[q, 0]):
        j = lng[q, 1 + n]
        lo = evlos[q, j]
        hi = lng[q, 1 + LONG_ROWS + n]
        for i in range(lo, hi):  # the envelope widens: entries not set by the lanes
            qi = qm[i]
            for c in range(_u(lo), _u(first[i])):
                qi[c] = 0.0
        _acc_stored(qm, qv, first, evrs[q, j], 0.0, lo, hi, lzz[q, n] * lzz[q, n])


@njit
@no_type_check
def _lane_dark(ql, fu, dark, g_da, g_sh2, nl, m):
    """The dark-channel prior of each pixel (`solve_pixels`' one-pixel code, weights
    `g_da[l] · dark[c] / g_sh2[l]`) in the lane layout."""
    lanes = _lane_index(nl)
    for c in range(m - 1):
        for lane in range(4):
            src = lanes[lane]
            wd2 = g_da[src] * dark[c] / g_sh2[src]
            ql[4 * (c * m + c) + lane] += wd2
            ql[4 * ((c + 1) * m + c + 1) + lane] += wd2
            ql[4 * ((c + 1) * m + c) + lane] -= wd2
        if c < fu[c + 1]:
            fu[c + 1] = c


@njit(slp=True)
@no_type_check
def _lane_priors(ql, fu, spec, spec_first, g_spec_w, nl, ridge_rel, spec_trace, m):
    """:func:`_add_priors` of the four pixels (prior weights `g_spec_w`) in the lane
    layout, the same operations per lane."""
    l0, l1, l2, l3 = _lane_index(nl)
    w0 = g_spec_w[l0]
    w1 = g_spec_w[l1]
    w2 = g_spec_w[l2]
    w3 = g_spec_w[l3]
    t0 = t1 = t2 = t3 = 0.0
    for i in range(m):
        e = _u(4 * (i * m + i))
        t0 += ql[e]
        t1 += ql[e + _u(1)]
        t2 += ql[e + _u(2)]
        t3 += ql[e + _u(3)]
    d0 = ridge_rel * ((t0 + w0 * spec_trace) / m + 1e-30)
    d1 = ridge_rel * ((t1 + w1 * spec_trace) / m + 1e-30)
    d2 = ridge_rel * ((t2 + w2 * spec_trace) / m + 1e-30)
    d3 = ridge_rel * ((t3 + w3 * spec_trace) / m + 1e-30)
    for i in range(m):
        si = spec[i]
        base = _u(4 * i * m)
        for j in range(_u(spec_first[i]), _u(i + 1)):
            f = base + _u(4) * j
            v = si[j]
            ql[f] += w0 * v
            ql[f + _u(1)] += w1 * v
            ql[f + _u(2)] += w2 * v
            ql[f + _u(3)] += w3 * v
        e = _u(4 * (i * m + i))
        ql[e] += d0
        ql[e + _u(1)] += d1
        ql[e + _u(2)] += d2
        ql[e + _u(3)] += d3
        if spec_first[i] < fu[i]:
            fu[i] = spec_first[i]


@njit(slp=True)
@no_type_check
def _solve_lanes(ql, qvl, fu, ptr, lf, inv, xl, fail, m):
    """The unconstrained minimisers of the four systems `ql`, `qvl` (lane layout,
    envelope `fu`) side by side: the envelope Cholesky's loops are short, and their
    fixed cost is then paid once for four pixels. Lane l's answer is `xl[4 i + l]`,
    `fail[l]` when its factorisation failed. `lf` (as `ql`), `inv`, `ptr` are work
    space."""
    for i in range(m):
        ptr[i] = i * m + fu[i]
    for lane in range(4):
        fail[lane] = False
    _lane_factor(ql, ptr, fu, lf, inv, fail, m)
    _lane_solve(lf, ptr, fu, inv, qvl, xl, m)


@njit(slp=True)
@no_type_check
def _lane_gradient(ql, qvl, fu, xl, gl, m):
    """g = Q x + q of the four systems (lane layout, x and g as 4 i + l), as
    :func:`_gradient`."""
    for i in range(m):
        e = _u(4 * (i * m + i))
        c = _u(4 * i)
        gl[c] = qvl[c] + ql[e] * xl[c]
        gl[c + _u(1)] = qvl[c + _u(1)] + ql[e + _u(1)] * xl[c + _u(1)]
        gl[c + _u(2)] = qvl[c + _u(2)] + ql[e + _u(2)] * xl[c + _u(2)]
        gl[c + _u(3)] = qvl[c + _u(3)] + ql[e + _u(3)] * xl[c + _u(3)]
    for i in range(m):
        c = _u(4 * i)
        x0 = xl[c]
        x1 = xl[c + _u(1)]
        x2 = xl[c + _u(2)]
        x3 = xl[c + _u(3)]
        g0 = g1 = g2 = g3 = 0.0
        base = _u(4 * i * m)
        for j in range(_u(fu[i]), _u(i)):
            f = base + _u(4) * j
            o = _u(4) * j
            g0 += ql[f] * xl[o]
            g1 += ql[f + _u(1)] * xl[o + _u(1)]
            g2 += ql[f + _u(2)] * xl[o + _u(2)]
            g3 += ql[f + _u(3)] * xl[o + _u(3)]
            _lane_update(gl, o, ql, f, x0, x1, x2, x3)
        gl[c] += g0
        gl[c + _u(1)] += g1
        gl[c + _u(2)] += g2
        gl[c + _u(3)] += g3


@njit(inline=True)
@no_type_check
def _lane_unpack(ql, qvl, fu, lane, qm, qv, first, m):
    """Pixel `lane`'s Q (inside the envelope `fu`), q and envelope out of the lane
    layout, for the one-pixel code."""
    for i in range(m):
        qv[i] = qvl[4 * i + lane]
        first[i] = fu[i]
        qi = qm[i]
        for j in range(fu[i], i + 1):
            qi[j] = ql[4 * (i * m + j) + lane]


@njit
@no_type_check
def _column_grid(off, par, ipar, table, span_lo, span_hi, cspan, crow):
    """The band on the time grid of one sweep of a column (offset `off`), for
    :func:`_lowpass_rows`: at local grid point jj, the table rows interpolated,
    ``crow[jj, c - lo] = (1 - f) table[b, c] + f table[b + 1, c]`` over the span
    ``[lo, hi) = cspan[jj]`` (hi ≤ lo: no band). The grid's band depends on the
    column only, and the fused path hands a worker the pixels column by column
    (:func:`._fused.solve_fused`), so each column's grid is formed once for all its
    pixels: formed per pixel, its table loads (rows ~3 kB apart from one grid point
    to the next, in a 4 MB table) stalled the photoreceptor rows (sampling
    profile), and the interpolation was done twice per point."""
    n = ipar[I_SAMPLES]
    dt = par[P_PERIOD] / n
    ntab = table.shape[0]
    for jj in range(n):
        b, f = _band_local(jj * dt, off, par, ntab)
        if b < 0:
            cspan[jj, 0] = 0
            cspan[jj, 1] = 0
            continue
        lo = min(span_lo[b], span_lo[b + 1])
        hi = max(span_hi[b], span_hi[b + 1])
        cspan[jj, 0] = lo
        cspan[jj, 1] = hi
        t0 = table[b]
        t1 = table[b + 1]
        g0 = 1.0 - f
        row = crow[jj]
        for c in range(lo, hi):
            row[c - lo] = t0[c] * g0 + t1[c] * f


# exp and log in arithmetic that vectorises (AVX2 has no packed conversions between
# float64 and int64, so the integer parts go through the bits of float64 numbers:
# 1.5·2^52 added to a float64 below 2^51 in magnitude leaves the rounded integer in
# its low bits). Both within 1 ulp of libm over their ranges here
# (tests/reconstruction/test_fused.py).
_LN2_HI = 6.93147180369123816490e-01  # ln 2 in two parts: k·ln2_hi is exact
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_ROUND = 6755399441055744.0  # 1.5 · 2^52
_SQRT_HALF_BITS = 0x3FE6A09E667F3BCD  # the bits of √2 / 2
_EXP_TAYLOR = tuple(1.0 / math.factorial(i) for i in range(13, -1, -1))  # 1/13! … 1
_ATANH_SERIES = tuple(1.0 / i for i in range(23, 2, -2))  # 1/23, 1/21, … 1/3


@njit(inline=True)
@no_type_check
def _horner(coefs, x):
    """The polynomial with coefficients `coefs` (highest power first) at `x` (a loop
    of constant length over a tuple: unrolled, so the caller's loop vectorises)."""
    p = 0.0
    for c in coefs:
        p = p * x + c
    return p


@njit(inline=True)
@no_type_check
def _exp_rows(a, r, n):
    """`a[r, :n] = exp(a[r, :n])` for arguments ≤ 700, those below −700 as −700
    (exp ≈ 1e-304: what the photoreceptor recursion treats as a restart like 0);
    row 0 of `a` (C-contiguous, 2-D) is overwritten. x = k ln 2 + f, |f| ≤ ln2/2:
    e^f by its Taylor polynomial to degree 13 (error < 1e-17 there), 2^k from k's
    bits."""
    bits = a.view(np.uint64)
    for j in range(n):
        v = max(a[r, j], -700.0)
        t = v * _INV_LN2 + _ROUND
        kf = t - _ROUND
        f = (v - kf * _LN2_HI) - kf * _LN2_LO
        a[r, j] = _horner(_EXP_TAYLOR, f)
        a[0, j] = t
    for j in range(n):  # 2^k: k + 1023 into the exponent field
        bits[0, j] = (bits[0, j] + np.uint64(1023)) << np.uint64(52)
    for j in range(n):
        a[r, j] *= a[0, j]


@njit(inline=True)
@no_type_check
def _log_rows(a, src, dst, n):
    """`a[dst, :n] = log(a[src, :n])` for positive normal numbers; row 0 of `a`
    (C-contiguous, 2-D) is overwritten. x = 2^k m with m in [√2/2, √2) from x's
    bits; log m = 2 atanh(s), s = (m − 1)/(m + 1), |s| < 0.172, by its series to
    s^23 (error < 1e-18)."""
    bits = a.view(np.uint64)
    half = np.uint64(_SQRT_HALF_BITS)
    mant = np.uint64(0xFFFFFFFFFFFFF)
    shift = np.uint64(0x4000000000000000)  # keeps the difference positive
    k_bits = np.uint64(0x4338000000000000 - 1024)  # k + 1024 as float64 bits
    for j in range(n):
        ix = bits[src, j] - half + shift
        bits[0, j] = (ix & mant) + half
        bits[dst, j] = (ix >> np.uint64(52)) + k_bits
    for j in range(n):
        k = a[dst, j] - _ROUND
        f = a[0, j] - 1.0
        s = f / (2.0 + f)
        z = s * s
        p = _horner(_ATANH_SERIES, z)
        a[dst, j] = k * _LN2_HI + (2.0 * s + (2.0 * s * z * p + k * _LN2_LO))


@njit(inline=True)
@no_type_check
def _lowpass_point_terms(a, n, first, dt, d_w, log_eps):
    """From each grid point's intensity I in `a[1, :n]`: its decay over the step
    exp(-dt I / d_w) into `a[1]` (0 for the first `first` entries: the grid's first
    point, of each lane), log(I + ε) into `a[2]` and 1 / (I + ε) into `a[3]`; each
    in a pass of its own that LLVM vectorises (_exp_rows, _log_rows: libm's scalar
    calls were ~40 % of the photoreceptor rows' time; row 0 of `a` is their work
    space)."""
    for j in range(n):
        inten = a[1, j]
        a[3, j] = inten + log_eps
        a[1, j] = -dt * inten / d_w
    _exp_rows(a, 1, n)
    for j in range(first):
        a[1, j] = 0.0
    _log_rows(a, 3, 2, n)
    for j in range(n):
        a[3, j] = 1.0 / a[3, j]


@njit(inline=True)
@no_type_check
def _lowpass_queries(tr, k, phase, dt, g_n, eta, fq, lane, qh, apps, a_w, n_app,
                     n_sweep):  # fmt: skip
    """The queries of :func:`_lowpass_rows` of one pixel (`lane` of its group): event
    i's row of `fq` (zeroed here) gathers F at its time with weight +1 and at its
    reference with weight −1, the difference the event row needs. A query at grid
    position p = j + f (j = ⌊p⌋) takes (1 - f) F_j + f F_{j+1}: two applications,
    each put into the list of its grid point (`qh[j]`: the point's last
    application, -1 for none; `apps[a]`: the application before it in that list,
    then its lane and row; `a_w[a]`: its signed weight, ±(1 - f) or ±f), numbered
    from `n_app` on. Returns the grid points F is needed on (up to the last query's
    point + 1) and the new count of applications.

    A pixel's first reference may lie before the recording (a carried one,
    `reconstruct(reference_us=...)`: `phase` < 0), off the grid. It is read one
    period (`n_sweep` points) later, in the recording's first sweep: the band's
    schedule repeats with the period, so the filter started a sweep before the
    reference sees the light the grid's own filter, started at the recording, sees
    a sweep later — the same inputs from the same restart, hence the same value.
    (Before 2026-11-29 it was clamped to the grid's first point, the baseline; the
    rows of a carried reference then said what the baseline's say.)"""
    g_end = 1
    for q in range(2 * k):
        i = q // 2
        if q % 2 == 0:
            t = tr[i]
            sign = 1.0
            fq[i, :] = 0.0
        else:
            t = 0.0 if i == 0 else tr[i - 1] + eta
            sign = -1.0
        pos = (t + phase) / dt
        if pos < 0.0:  # (a carried reference before the recording: see below)
            pos += n_sweep
        pos = min(max(pos, 0.0), g_n - 1.0)
        j = min(np.int64(math.floor(pos)), g_n - 2)
        g_end = max(g_end, j + 2)
        for h in range(2):
            apps[n_app, 0] = qh[j + h]
            apps[n_app, 1] = lane
            apps[n_app, 2] = i
            a_w[n_app] = sign * ((pos - j) if h == 1 else 1.0 - (pos - j))
            qh[j + h] = n_app
            n_app += 1
    return g_end, n_app


@njit(inline=True)
@no_type_check
def _apply_queries(a, apps, a_w, fqs, v, lanes, scales, vlo, vhi):
    """The query shares of one grid point, from application `a` on along its list
    (:func:`_lowpass_queries`): each adds its weight times F = S V (lane l's
    running scale S in `scales[l]`) to its query's row (:func:`_lowpass_query`)."""
    while a >= 0:
        lane = apps[a, 1]
        _lowpass_query(
            fqs[lane, apps[a, 2]], scales[lane] * a_w[a], v, lane, lanes, vlo, vhi
        )  # fmt: skip
        a = apps[a, 0]


@njit(inline=True)
@no_type_check
def _lowpass_query(row, wq, v, lane, lanes, vlo, vhi):
    """row += wq F: a query's share of the filtered values, from channel 0 and the
    touched channels [vlo, vhi) of V (zero elsewhere). Channel c of V is
    `v[lanes c + lane]`: `lanes=1, lane=0` for :func:`_lowpass_rows`' V, 4 for the
    lane layout of :func:`_lane_lowpass_rows`."""
    row[0] += wq * v[lane]
    for c in range(_u(vlo + 1), _u(vhi + 1)):
        row[c] += wq * v[_u(lanes) * c + _u(lane)]


@njit
@no_type_check
def _lowpass_rows(
    x0, tr, step, w_log, k, phase, par, ipar, cspan, crow, vv, fq, qh, apps, a_w, sc,
    evr, evc, evlo, evhi, lp_f,
):  # fmt: skip
    """Event rows of the photoreceptor model linearised at `x0`
    (:func:`._problem._lowpass_rows`): the filtered $[\\log L, a/L]$ on the rig's
    time grid, differenced between each event's time `tr[i]` and its reference
    ($τ_{i-1} + η$, the recorded times), weighted by `w_log`, into `evr`/`evc`.

    The filter $F_j = α_j F_{j-1} + (1-α_j) s_j$ runs as $F = S V$ with a running
    scale $S = \\prod α$ (renormalised before it underflows), so a step costs the
    band's span, not M + 1; F is formed only at the grid points the queries need,
    over the channels the band has touched so far. What a grid point needs that does
    not depend on the earlier ones (intensity, decay, logarithm) is computed first,
    in short passes over all points, into `lp_f`. The band at each point comes from
    the column's grid `cspan`/`crow` (:func:`_column_grid`). `fq` (1, ≥ k, M + 1):
    each event's row of filtered differences; `qh`, `apps`, `a_w`: the queries'
    lists per grid point (:func:`_lowpass_queries`; `qh` ≥ the grid's points); `sc`
    (≥ 1) work space."""
    m = x0.size
    n = ipar[I_SAMPLES]
    period = par[P_PERIOD]
    dt = period / n
    g_n = ipar[I_SWEEPS] * n + 1
    d_w = max(par[P_DW], 1e-6)
    eta = par[P_ETA]
    qh[:g_n] = -1
    # F is needed up to the last query's grid point, g_end - 1
    g_end, _ = _lowpass_queries(tr, k, phase, dt, g_n, eta, fq[0], 0, qh, apps, a_w, 0,
                                n)  # fmt: skip
    vv[:] = 0.0
    scale = 1.0
    # First what a grid point needs that does not depend on the earlier points, in
    # short passes over all points: one point's intensity and transcendental
    # functions are a long chain of latencies, and in one loop with the recursion
    # they would not overlap from one point to the next (measured: the call took
    # twice as long). The intensity at x0 (four partial sums, as _dot1):
    for j in range(g_end):
        row = crow[j % n]
        lo = cspan[j % n, 0]
        n4 = max(cspan[j % n, 1] - lo, 0) // 4
        s0 = s1 = s2 = s3 = 0.0
        for q in range(_u(n4)):
            c = _u(4) * q
            v = _u(lo) + c
            s0 += row[c] * x0[v]
            s1 += row[c + _u(1)] * x0[v + _u(1)]
            s2 += row[c + _u(2)] * x0[v + _u(2)]
            s3 += row[c + _u(3)] * x0[v + _u(3)]
        for c in range(_u(4 * n4), _u(max(cspan[j % n, 1] - lo, 0))):
            s0 += row[c] * x0[_u(lo) + c]
        inten = par[P_BASE_REL] + ((s0 + s1) + (s2 + s3))
        lp_f[1, j] = max(inten, 0.0)
    _lowpass_point_terms(lp_f, g_end, 1, dt, d_w, par[P_LOG_EPS])
    # Then the recursion: V over the band's span, and the queries.
    vlo = m  # channels V has touched: [vlo, vhi)
    vhi = 0
    dtw = dt / d_w
    for j in range(g_end):
        alpha = lp_f[1, j]
        y_prev = scale * vv[0]  # the filtered log at the point before
        if alpha < 1e-200:  # F forgets its past (below 1e-200 of it): restart
            for c in range(m + 1):
                vv[c] = 0.0
            scale = 1.0
        else:
            if scale * alpha < 1e-200:  # renormalise V before S underflows
                for c in range(m + 1):
                    vv[c] *= scale
                scale = 1.0
            scale *= alpha
        inv = 1.0 / scale  # (a restart: 1, and the weight 1 - alpha)
        wgt = (1.0 - alpha) * inv
        vv[0] += wgt * lp_f[2, j]
        lo = cspan[j % n, 0]
        hi = cspan[j % n, 1]
        if hi > lo:
            row = crow[j % n]
            # The band's weight in the Jacobian: log's slope and the decay's part
            # (:func:`._problem._lowpass_rows`), in V's scale.
            wl = wgt * lp_f[3, j] - (y_prev - lp_f[2, j]) * alpha * dtw * inv
            for c in range(_u(hi - lo)):
                vv[_u(lo + 1) + c] += wl * row[c]
            vlo = min(vlo, lo)
            vhi = max(vhi, hi)
        # F_j's shares of the queries on [j - 1, j] and [j, j + 1] (V is zero
        # outside channel 0 and the touched channels).
        if qh[j] >= 0:
            sc[0] = scale
            _apply_queries(qh[j], apps, a_w, fq, vv, 1, sc, vlo, vhi)
    _lowpass_finish(fq[0], step, x0, w_log, k, evr, evc, evlo, evhi)


@njit(inline=True)
@no_type_check
def _lowpass_finish(fq, step, x0, w_log, k, evr, evc, evlo, evhi):
    """The event rows of :func:`_lowpass_rows` from the filtered differences at the
    queries, `fq[i]` for event i (channel 0: the filtered log, then the channels).
    Sums and the largest entry in four parts each, so that the loops vectorise (one
    running sum was a chain of dependent additions, ~20 % of the photoreceptor
    pass); the entries below `TRIM` of the largest are cut at both ends of the row."""
    m = x0.size
    m4 = m // 4
    for i in range(k):
        d = fq[i]
        ri = evr[i]
        s0 = s1 = s2 = s3 = 0.0
        b0 = b1 = b2 = b3 = 0.0
        for q in range(_u(m4)):
            c = _u(4) * q
            v0 = d[c + _u(1)]
            v1 = d[c + _u(2)]
            v2 = d[c + _u(3)]
            v3 = d[c + _u(4)]
            s0 += v0 * x0[c]
            s1 += v1 * x0[c + _u(1)]
            s2 += v2 * x0[c + _u(2)]
            s3 += v3 * x0[c + _u(3)]
            b0 = max(b0, abs(v0))
            b1 = max(b1, abs(v1))
            b2 = max(b2, abs(v2))
            b3 = max(b3, abs(v3))
        for c in range(_u(4 * m4), _u(m)):
            v0 = d[c + _u(1)]
            s0 += v0 * x0[c]
            b0 = max(b0, abs(v0))
        cut = TRIM * max(max(b0, b1), max(b2, b3))
        lo = m
        hi = 0
        for c in range(m):  # (integer minimum and maximum: vectorised)
            big = abs(d[c + 1]) > cut
            lo = min(lo, c if big else m)
            hi = max(hi, c + 1 if big else 0)
        w = w_log[i]
        for c in range(m):
            ri[c] = d[c + 1] * w if lo <= c < hi else 0.0
        evc[i] = ((d[0] - step[i]) - ((s0 + s1) + (s2 + s3))) * w
        evlo[i] = lo if hi > lo else 0
        evhi[i] = hi if hi > lo else 0


@njit(slp=True)
@no_type_check
def _lane_lowpass_rows(
    todo, nl, xs, trs, steps, w_logs, ks, phases, par, ipar, cspan, crow, vl, fqs,
    qh, apps, a_w, evrs, evcs, evlos, evhis, lpl, x4, st,
):  # fmt: skip
    """:func:`_lowpass_rows` of the group's pixels marked in `todo`, side by side, one
    per lane: they share a column offset (the fused path hands out pixels column
    by column), so the band on the grid (`cspan`, `crow`) is theirs alike, and each
    grid point's intensity, decay, logarithm and filter step is one four-lane
    operation instead of four loops of the band's span. Each pixel's numbers go
    through the same operations in the same order as in :func:`_lowpass_rows`, so
    its rows are the same to the last bit (tests/reconstruction/test_fused.py).
    Lane l of channel c of V is `vl[4 c + l]`; `x4` holds x0 so; `lpl` is
    `_lowpass_rows`' `lp_f` with four lanes per grid point; `st` (float64, ≥ 8)
    work space; `qh`, `apps`, `a_w` the queries' lists per grid point, all lanes'
    in one (:func:`_lowpass_queries`). The grid runs to the group's last query; a
    pixel's queries complete where its own would."""
    m = xs.shape[1]
    n = ipar[I_SAMPLES]
    dt = par[P_PERIOD] / n
    g_n = ipar[I_SWEEPS] * n + 1
    d_w = max(par[P_DW], 1e-6)
    eta = par[P_ETA]
    g_end = 1
    n_app = 0
    qh[:g_n] = -1
    for lane in range(4):
        live = lane < nl and todo[lane]
        for c in range(m):
            x4[4 * c + lane] = xs[lane, c] if live else 0.0
        if live:
            g_lane, n_app = _lowpass_queries(
                trs[lane], ks[lane], phases[lane], dt, g_n, eta, fqs[lane], lane, qh,
                apps, a_w, n_app, n,
            )  # fmt: skip
            g_end = max(g_end, g_lane)
    # The intensity at x0 (each lane's four partial sums, as _lowpass_rows').
    base_rel = par[P_BASE_REL]
    jn = 0  # j's point within its sweep (j % n, without a division per point)
    for j in range(g_end):
        row = crow[jn]
        lo = cspan[jn, 0]
        span = max(cspan[jn, 1] - lo, 0)
        n4 = span // 4
        a0 = a1 = a2 = a3 = 0.0  # partial sum 0 of the four lanes
        b0 = b1 = b2 = b3 = 0.0
        c0 = c1 = c2 = c3 = 0.0
        d0 = d1 = d2 = d3 = 0.0
        for q in range(_u(n4)):
            c = _u(4) * q
            v = _u(4) * (_u(lo) + c)
            r = row[c]
            a0, a1, a2, a3 = _lane_axpy(a0, a1, a2, a3, x4, v, r, r, r, r)
            r = row[c + _u(1)]
            b0, b1, b2, b3 = _lane_axpy(b0, b1, b2, b3, x4, v + _u(4), r, r, r, r)
            r = row[c + _u(2)]
            c0, c1, c2, c3 = _lane_axpy(c0, c1, c2, c3, x4, v + _u(8), r, r, r, r)
            r = row[c + _u(3)]
            d0, d1, d2, d3 = _lane_axpy(d0, d1, d2, d3, x4, v + _u(12), r, r, r, r)
        for c in range(_u(4 * n4), _u(span)):
            r = row[c]
            a0, a1, a2, a3 = _lane_axpy(
                a0, a1, a2, a3, x4, _u(4) * (_u(lo) + c), r, r, r, r
            )  # fmt: skip
        e = _u(4 * j)
        lpl[1, e] = max(base_rel + ((a0 + b0) + (c0 + d0)), 0.0)
        lpl[1, e + _u(1)] = max(base_rel + ((a1 + b1) + (c1 + d1)), 0.0)
        lpl[1, e + _u(2)] = max(base_rel + ((a2 + b2) + (c2 + d2)), 0.0)
        lpl[1, e + _u(3)] = max(base_rel + ((a3 + b3) + (c3 + d3)), 0.0)
        jn = jn + 1 if jn + 1 < n else 0
    _lowpass_point_terms(lpl, 4 * g_end, 4, dt, d_w, par[P_LOG_EPS])
    # The recursion, four lanes at a time (st[0:4]: each lane's running scale S,
    # st[4:8]: its weight of the band at this point).
    for c in range(4 * (m + 1)):
        vl[c] = 0.0
    for lane in range(4):
        st[lane] = 1.0
    vlo = m
    vhi = 0
    jn = 0
    dtw = dt / d_w
    for j in range(g_end):
        for lane in range(4):
            alpha = lpl[1, 4 * j + lane]
            scale = st[lane]
            y_prev = scale * vl[lane]
            if alpha < 1e-200:  # F forgets its past: restart
                for c in range(m + 1):
                    vl[4 * c + lane] = 0.0
                scale = 1.0
            else:
                if scale * alpha < 1e-200:  # renormalise V before S underflows
                    for c in range(m + 1):
                        vl[4 * c + lane] *= scale
                    scale = 1.0
                scale *= alpha
            inv = 1.0 / scale
            wgt = (1.0 - alpha) * inv
            st[lane] = scale
            lg = lpl[2, 4 * j + lane]
            vl[lane] += wgt * lg
            st[4 + lane] = wgt * lpl[3, 4 * j + lane] - (y_prev - lg) * alpha * dtw * inv
        lo = cspan[jn, 0]
        hi = cspan[jn, 1]
        if hi > lo:
            row = crow[jn]
            w0, w1, w2, w3 = st[4], st[5], st[6], st[7]
            for c in range(_u(hi - lo)):
                r = row[c]
                _lane_add(vl, _u(4) * (_u(lo + 1) + c), r, r, r, r, w0, w1, w2, w3)
            vlo = min(vlo, lo)
            vhi = max(vhi, hi)
        jn = jn + 1 if jn + 1 < n else 0
        if qh[j] >= 0:  # the lanes' query shares at this point
            _apply_queries(qh[j], apps, a_w, fqs, vl, 4, st, vlo, vhi)
    for lane in range(nl):
        if todo[lane]:
            _lowpass_finish(
                fqs[lane], steps[lane], xs[lane], w_logs[lane], ks[lane], evrs[lane],
                evcs[lane], evlos[lane], evhis[lane],
            )  # fmt: skip


@njit(inline=True)
@no_type_check
def _median(a, k, buf):
    """The median of `a[:k]` (k ≥ 1), as `np.median`: the middle value, or the
    mean of the two middle ones; sorted by insertion in `buf` (k is a pixel's
    event count, a few dozen: no allocation, unlike `np.median`'s copy)."""
    for i in range(k):
        v = a[i]
        j = i
        while j > 0 and buf[j - 1] > v:
            buf[j] = buf[j - 1]
            j -= 1
        buf[j] = v
    h = k // 2
    return buf[h] if k % 2 == 1 else (buf[h - 1] + buf[h]) / 2


@njit(inline=True)
@no_type_check
def _row_z(evr, evc, evlo, evhi, sigma, x, i):
    """|residual| of event row i at x, in standard deviations of the row."""
    ri = evr[i]
    zi = evc[i]
    for j in range(evlo[i], evhi[i]):
        zi += ri[j] * x[j]
    return abs(zi / sigma[i])


@njit
@no_type_check
def _assemble(
    restore, qm, qv, qd, qvd, first, evr, evc, evlo, evhi, u, k, spec, spec_first,
    spec_w, par,
):  # fmt: skip
    """Q, q ← (the kept drift part, if `restore`) + the event rows weighted by `u` +
    the priors."""
    if restore:
        _restore_drift(qm, qv, qd, qvd, first)
    _add_events(qm, qv, first, evr, evc, evlo, evhi, u, k)
    _add_priors(qm, first, spec, spec_first, spec_w, par[P_RIDGE], par[P_SPEC_TRACE])


@njit(inline=True)
@no_type_check
def _write_answer(r, steps, qm, first, qv, x, gr, out_x, out_kkt, out_steps):
    """Pixel r's answer x, its KKT residual and active-set steps (NaN, NaN, −1 when
    a factorisation failed)."""
    m = qv.size
    if steps < 0:
        for i in range(m):
            out_x[r, i] = np.nan
        out_kkt[r] = np.nan
        out_steps[r] = -1
        return
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


@njit(inline=True)
@no_type_check
def _write_lanes(
    r0, nl, steps, ql, qvl, fu, xs, xl, gl, out_x, out_kkt, out_steps, lng, lzz, evrs,
    evlos, dg,
):  # fmt: skip
    """:func:`_write_answer` of the group's pixels `r0 + l`, their systems in the lane
    layout (the gradients of the four side by side) plus their long rows (`lng`, `lzz`,
    :func:`_hold_long_rows`; none without them). `dg` (M) is work space."""
    m = xs.shape[1]
    lanes = _lane_index(nl)
    for lane in range(4):
        x = xs[lanes[lane]]
        for i in range(m):
            xl[4 * i + lane] = x[i]
    _lane_gradient(ql, qvl, fu, xl, gl, m)
    for lane in range(nl):
        r = r0 + lane
        if steps[lane] < 0:
            for i in range(m):
                out_x[r, i] = np.nan
            out_kkt[r] = np.nan
            out_steps[r] = -1
            continue
        x = xs[lane]
        for i in range(m):
            dg[i] = ql[4 * (i * m + i) + lane]
        for n in range(lng[lane, 0]):  # g += s r (r·x); Q's diagonal += s r²
            row = evrs[lane, lng[lane, 1 + n]]
            lo = evlos[lane, lng[lane, 1 + n]]
            s2 = lzz[lane, n] * lzz[lane, n]
            t = 0.0
            for i in range(lo, lng[lane, 1 + LONG_ROWS + n]):
                t += row[i] * x[i]
            for i in range(lo, lng[lane, 1 + LONG_ROWS + n]):
                gl[4 * i + lane] += s2 * row[i] * t
                dg[i] += s2 * row[i] * row[i]
        qmax = 0.0
        for i in range(m):
            qmax = max(qmax, abs(dg[i]))
        kkt = 0.0
        for i in range(m):
            g = gl[4 * i + lane]
            kkt = max(kkt, abs(x[i] - max(x[i] - g / qmax, 0.0)))
            out_x[r, i] = x[i]
        out_kkt[r] = kkt
        out_steps[r] = steps[lane]


@njit(inline=True)
@no_type_check
def _solve_group(
    nl, todo, qms, qvs, firsts, xs, steps, ql, qvl, fu, ptr, lfl, invl, xl, fail,
    free, lf, inv, p, gr, par, max_iters, lng, lzz, evrs, evlos, lw,
):  # fmt: skip
    """The box QPs of the group's pixels marked in `todo`, answers into `xs`, steps
    into `steps` (−1: a factorisation failed). One pixel (`qms`, `qvs`, `firsts`):
    :func:`_box_qp`. Four (their systems in the lane layout `ql`, `qvl`, `fu`): their
    unconstrained minimisers side by side (:func:`_solve_lanes`); a pixel whose
    minimiser has a negative channel goes on from it with :func:`_box_qp`'s
    active-set steps on its own system, taken out of the lane layout, and a pixel
    whose lane factorisation failed runs `_box_qp` from the start, as the one-pixel
    path does. The lanes' Q leaves out the pixels' long rows listed in `lng`
    (:func:`_hold_long_rows`; none without them), added by :func:`_lane_long_rows`
    (and into a pixel's own Q when it leaves the lanes)."""
    m = qvs.shape[1]
    tol = par[P_TOL]
    if qms.shape[0] == 1:
        if todo[0]:
            # have_x = bool(0): typed bool as at the call below, not the literal
            # False (numba would compile _box_qp twice, ~2.5 s on a clean clone).
            steps[0] = _box_qp(
                qms[0], qvs[0], firsts[0], free, lf, inv, xs[0], p, gr, tol,
                max_iters, bool(0),
            )  # fmt: skip
        return
    _solve_lanes(ql, qvl, fu, ptr, lfl, invl, xl, fail, m)
    _lane_long_rows(nl, todo, fail, lng, lzz, evrs, evlos, ptr, fu, lfl, invl, xl, lw, m)
    for lane in range(nl):
        if not todo[lane]:
            continue
        x = xs[lane]
        neg = False
        for i in range(m):
            v = xl[4 * i + lane]
            x[i] = v
            if v < 0.0:
                neg = True
        if neg or fail[lane]:
            _lane_unpack(ql, qvl, fu, lane, qms[lane], qvs[lane], firsts[lane], m)
            _add_long_rows(
                qms[lane], qvs[lane], firsts[lane], lane, lng, lzz, evrs, evlos
            )  # fmt: skip
            steps[lane] = _box_qp(
                qms[lane], qvs[lane], firsts[lane], free, lf, inv, x, p, gr, tol,
                max_iters, not fail[lane],
            )  # fmt: skip
        else:  # what _box_qp does with a minimiser inside the box
            for i in range(m):
                if x[i] <= 0.0:
                    x[i] = 0.0
            steps[lane] = 0


@njit(inline=True)
@no_type_check
def _lane_assemble(
    restore, nl, ql, qvl, qdl, qvdl, fu, evrs, evlos, evhis, evcs, zzs, g_k, rl, sw, st,
    spec, spec_first, g_spec_w, par, split, evxs, lng, lzz,
):  # fmt: skip
    """:func:`_assemble` of the group's four pixels in the lane layout: Q, q ← (the
    kept drift part, if `restore`) + each pixel's event rows weighted by its `zzs` +
    the priors. With `split`, each pixel's long rows (`LONG_SPAN`) add their part of
    q only; their part of Q is left to :func:`_lane_long_rows` (listed in `lng`,
    `lzz`: :func:`_hold_long_rows`)."""
    m = spec.shape[0]
    if restore:
        _lane_copy(qdl, qvdl, ql, qvl, fu, m)
    if split:
        _hold_long_rows(nl, evlos, evhis, evxs, zzs, g_k, lng, lzz)
    nrows = max(g_k[:nl].max(), 0)  # the most event rows of the group's pixels
    _lane_rows(
        evrs, evlos, evhis, evcs, zzs, g_k, nl, nrows, rl, sw, st, ql, qvl, fu, m
    )  # fmt: skip
    if split:
        _restore_long_rows(nl, evhis, zzs, lng, lzz, evrs, evcs, evlos, qvl)
    _lane_priors(
        ql, fu, spec, spec_first, g_spec_w, nl, par[P_RIDGE], par[P_SPEC_TRACE], m
    )


@njit
@no_type_check
def solve_pixels(
    sel, starts, use, t_sorted, s_sorted, lead, col_off, width, thr_on, thr_off,
    table, tabsum, span_lo, span_hi, spec, spec_first, dark, par, ipar, out_x,
    out_kkt, out_steps, out_fit,
):  # fmt: skip
    """Assemble and solve the pixels `sel` (flat indices); their events are
    `t_sorted[starts[p] : starts[p] + use[p]]` (µs from the recording start, time
    order) with polarities `s_sorted`. Writes each pixel's x, KKT residual and
    active-set steps (-1: a factorisation failed, x is NaN).

    With the noise model (`ipar[I_NOISE]`) the event times are moved back by the
    photoreceptor's lag, the event rows weighted by their noise, the dark-channel
    prior added (`dark`: its per-difference weight before the noise share) and the
    robust reweighting run `ipar[I_ROBUST]` times — :func:`._problem.pixel_system`
    with `noise` and the reweighting of :func:`._pipeline._solve_chunk`.

    `out_fit` `(n, 3)`: with the noise model, each pixel's event rows at its answer —
    the largest |residual| in standard deviations of its row, that row's event index,
    and the sum of the squared residuals, each capped at the rejection level
    (`P_REJECT`); NaN without the noise model or where the solve failed
    (:func:`._pipeline.repair_strays` reads them)."""
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
    noisy_model = ipar[I_NOISE] != 0
    robust_steps = ipar[I_ROBUST] if noisy_model else 0
    peak = target == 1 or target == 3
    flat = target >= 2
    kmax = 1
    for r in range(sel.size):
        kmax = max(kmax, use[sel[r]])
    tt = np.empty(kmax)
    sgn = np.empty(kmax)
    thr = np.empty(kmax)
    sweep_of = np.empty(kmax, np.int64)
    bt = np.empty(kmax, np.int64)  # the band's table row and fraction at τ_i
    ft = np.empty(kmax)
    be = np.empty(kmax, np.int64)  # ... and at τ_i + η
    fe = np.empty(kmax)
    drift = np.empty(kmax)
    i_hat = np.empty(kmax)
    absz = np.empty(kmax)
    mbuf = np.empty(kmax)  # _median's work space
    lf = np.zeros((m, m))
    inv = np.zeros(m)
    row = np.zeros(m)
    free = np.ones(m, np.bool_)
    p = np.zeros(m)
    gr = np.zeros(m)
    lohi = np.zeros(2, np.int64)
    d_w = par[P_DW]
    lowpass = noisy_model and d_w > 0.0 and ipar[I_LOWPASS] > 0
    lp_passes = ipar[I_LOWPASS] if lowpass else 0
    n_query = 2 * kmax if lowpass else 1  # per pixel: each event's time, its reference
    n_grid = sweeps * ipar[I_SAMPLES] + 1 if lowpass else 1
    lp_f = np.zeros((4, n_grid))
    # The band on one sweep's time grid of the column last used (_column_grid).
    # (a row holds its span only: ~18 of M values, a quarter of the memory to cache)
    n_col = ipar[I_SAMPLES] if lowpass else 1
    w_col = 1
    for b in range(ntab - 1 if lowpass else 0):
        w_col = max(
            w_col,
            max(span_hi[b], span_hi[b + 1]) - min(span_lo[b], span_lo[b + 1]),
        )
    cspan = np.zeros((n_col, 2), np.int64)
    crow = np.zeros((n_col, w_col))
    col_done = np.nan
    vv = np.zeros(m + 1)
    fq = np.zeros((1, kmax if lowpass else 1, m + 1))  # a row per event
    keep_drift = robust_steps > 0 or lowpass
    # The pixels' systems are solved `ipar[I_LANES]` (1 or 4) at a time, side by
    # side (_solve_group); each pixel of a group keeps its own state.
    group = LANES if ipar[I_LANES] == LANES else 1
    qms = np.zeros((group, m, m))
    qvs = np.zeros((group, m))
    firsts = np.zeros((group, m), np.int64)
    xs = np.zeros((group, m))
    xprev = np.zeros((group, m))  # each pixel's answer before a Gauss–Newton pass
    lp_more = np.zeros(group, np.bool_)  # its last pass moved it by > lowpass_tol
    g_steps = np.zeros(group, np.int64)
    todo = np.zeros(group, np.bool_)
    g_k = np.zeros(group, np.int64)
    g_phase = np.zeros(group)
    g_off = np.zeros(group)
    g_spec_w = np.zeros(group)
    steps2 = np.empty((group, kmax))  # per pixel: steps of its events, …
    traws = np.empty((group, kmax))
    wns = np.empty((group, kmax))
    sigmas = np.empty((group, kmax))
    zzs = np.empty((group, kmax))
    evrs = np.zeros((group, kmax, m))  # … its kept event rows …
    evcs = np.zeros((group, kmax))
    evlos = np.zeros((group, kmax), np.int64)
    evhis = np.zeros((group, kmax), np.int64)
    evxs = np.zeros((group, kmax), np.bool_)  # … which refer to an earlier sweep …
    nd = group if keep_drift else 1
    qds = np.zeros((nd, m, m))  # … and its drift part
    qvds = np.zeros((nd, m))
    # Four pixels: their systems in the lane layout (see _lane_index), the
    # anti-drift rows kept per pixel and added side by side (_lane_rows).
    lanes = group > 1
    nsq = LANES * m * m if lanes else 1
    ql = np.zeros(nsq)
    qdl = np.zeros(nsq if keep_drift else 1)
    lfl = np.zeros(nsq)
    invl = np.zeros(LANES * m)
    qvl = np.zeros(LANES * m)
    qvdl = np.zeros(LANES * m)
    xl = np.zeros(LANES * m)
    gl = np.zeros(LANES * m)
    rl = np.zeros(LANES * ROWS_PER_PASS * m)
    sw = np.zeros(2 * LANES * ROWS_PER_PASS)
    rw = np.zeros(m + 8 * ROWS_PER_PASS, np.int64)  # _lane_rows' work space
    fu = np.arange(m)
    ptr = np.zeros(m, np.int64)
    fail = np.zeros(LANES, np.bool_)
    # The group's long event rows, kept out of the lanes' Q (_hold_long_rows,
    # _lane_long_rows): not with the photoreceptor rows (wide by nature).
    split = lanes and not lowpass and ipar[I_LONG] != 0
    lng = np.zeros((LANES, 1 + 2 * LONG_ROWS), np.int64)
    lzz = np.zeros((LANES, LONG_ROWS))
    lw = np.zeros((LONG_ROWS + 2, max(LANES * m, LONG_ROWS * (LONG_ROWS + 2))))
    # The photoreceptor pass of a group's pixels of one column side by side
    # (_lane_lowpass_rows).
    lane_lp = lowpass and group == LANES
    ng = group if lane_lp else 1
    vl = np.zeros(LANES * (m + 1) if lane_lp else 1)
    fqs = np.zeros((ng, kmax if lane_lp else 1, m + 1))
    # the queries' lists per grid point, for either (_lowpass_queries)
    qh = np.zeros(n_grid, np.int64)
    apps = np.zeros((2 * ng * n_query, 3), np.int64)  # two shares per query
    a_w = np.zeros(2 * ng * n_query)
    lpl = np.zeros((4, LANES * n_grid if lane_lp else 1))
    x4 = np.zeros(LANES * m)
    st = np.zeros(8)  # _lane_lowpass_rows' work space (also _lowpass_rows' `sc`)
    n_ad = sweeps * g if lanes else 1
    adrs = np.zeros((group, n_ad, m) if lanes else (1, 1, 1))
    adlo = np.zeros((group, n_ad), np.int64)
    adhi = np.zeros((group, n_ad), np.int64)
    adc = np.zeros((group, n_ad))
    ad_w = np.ones((group, n_ad))
    ad_n = np.full(group, n_ad)
    g_da = np.zeros(group)
    g_sh2 = np.ones(group)
    for r0 in range(0, sel.size, group):
        nl = min(group, sel.size - r0)
        if lanes:
            _lane_clear(ql, qvl, qdl, qvdl, keep_drift, fu, m)
        for lane in range(nl):
            qm = qms[lane]
            qv = qvs[lane]
            first = firsts[lane]
            step = steps2[lane]
            traw = traws[lane]
            wn = wns[lane]
            sigma = sigmas[lane]
            zz = zzs[lane]
            evr = evrs[lane]
            evc = evcs[lane]
            evlo = evlos[lane]
            evhi = evhis[lane]
            evx = evxs[lane]
            qd = qds[lane if keep_drift else 0]
            qvd = qvds[lane if keep_drift else 0]
            pix = sel[r0 + lane]
            k = use[pix]
            s0 = starts[pix]
            d = lead[pix]
            phase = -d
            off = col_off[pix % width]
            t_on, t_off = thr_on[pix], thr_off[pix]
            if not lanes:
                qm[:, :] = 0.0
                qv[:] = 0.0
                for i in range(m):
                    first[i] = i
            lohi[0] = m
            lohi[1] = 0
            # Events: steps and sweeps (from the recorded times); with a photoreceptor
            # lag, each time moved back by d_w / Î (Î from the steps alone), kept ordered.
            level = 0.0
            t_max = -np.inf
            for i in range(k):
                tt[i] = t_sorted[s0 + i] + d
                traw[i] = tt[i]
                sg = 1.0 if s_sorted[s0 + i] > 0 else -1.0
                sgn[i] = sg
                thr[i] = t_on if sg > 0 else t_off
                step[i] = sg * thr[i]
                sweep_of[i] = np.int64(math.floor((tt[i] + phase) / period))
                if noisy_model:
                    if i == 0 or sweep_of[i] != sweep_of[i - 1]:
                        level = 0.0
                    level += step[i]
                    delay = min(par[P_DW] * math.exp(-(log_base + level)), 5000.0)
                    t_max = max(t_max, tt[i] - delay)
                    tt[i] = t_max
            # Drift on monotone flanks and the level estimates (from the used times).
            prev_s = 0.0
            level = 0.0
            peak_i = base
            for i in range(k):
                sg = sgn[i]
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
            # The band at each event (τ_i) and at the end of its refractory period
            # (τ_i + η: the next event's reference and the anti-drift rows' "after"
            # point), looked up once for the event and the anti-drift rows.
            for i in range(k):
                bt[i], ft[i] = _band_at(tt[i], phase, off, par, ntab)
                be[i], fe[i] = _band_at(tt[i] + eta, phase, off, par, ntab)
            b_zero, f_zero = _band_at(0.0, phase, off, par, ntab)
            # Event rows [a(τ) - e^{σC} a(ρ); c'(1 - e^{σC})] / Î (× noise weight), kept.
            share = 0.0
            var_c = par[P_SIG_C] ** 2
            for i in range(k):
                ratio = math.exp(step[i])
                w = 1.0 / i_hat[i] if norm else 1.0
                t_ref = 0.0 if i == 0 else tt[i - 1] + eta
                if noisy_model:
                    gap = max(tt[i] - t_ref, 1.0)
                    slope = abs(step[i]) / gap
                    ideal = par[P_FLOOR] ** 2 + slope * slope / 6.0
                    var = var_c + 2.0 * par[P_SIG_T] ** 2 * slope * slope
                    wn[i] = math.sqrt(ideal / (ideal + var))
                    w *= wn[i]
                    sigma[i] = math.sqrt(ideal)
                    # (threshold noise alone: `_problem.pixel_system`'s share)
                    share += var_c / (ideal + var_c)
                b0, f0 = bt[i], ft[i]
                b1, f1 = (b_zero, f_zero) if i == 0 else (be[i - 1], fe[i - 1])
                ri = evr[i]
                lohi[0] = m
                lohi[1] = 0
                segs = ((b0, f0, w), (b1, f1, -w * ratio))
                _add_bands(ri, segs, table, span_lo, span_hi, lohi)
                evc[i] = w * base * (1.0 - ratio)
                evlo[i] = min(lohi[0], lohi[1])
                evhi[i] = lohi[1]
                # Its reference in the sweep before (a carried reference, or a
                # sweep boundary): the two bands lie far apart (LONG_SPAN).
                evx[i] = (d > 0.0) if i == 0 else sweep_of[i] != sweep_of[i - 1]
            lohi[0] = m
            lohi[1] = 0
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
                        ba, fa = be[prv], fe[prv]
                    if b_ev:
                        bb, fb = bt[nxt], ft[nxt]
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
                    rr = adrs[lane, s * g + j] if lanes else row
                    segs = (
                        (bg, fg, w_int),
                        (ba, fa, -w_int * ca),
                        (bb, fb, -w_int * cb),
                    )
                    _add_bands(rr, segs, table, span_lo, span_hi, lohi)
                    if lanes:  # kept, added with the group's (_lane_rows)
                        adlo[lane, s * g + j] = lohi[0]
                        adhi[lane, s * g + j] = lohi[1]
                        adc[lane, s * g + j] = w_int * c_row
                        lohi[0] = m
                        lohi[1] = 0
                    elif lohi[1] > lohi[0]:
                        _accumulate(row, w_int * c_row, lohi, qm, qv, first)
                    else:
                        lohi[0] = m
                        lohi[1] = 0
            for i in range(k):
                zz[i] = 1.0
            spec_w = par[P_ASPEC] / (s_hat * s_hat) if norm else par[P_ASPEC]
            g_k[lane] = k
            g_phase[lane] = phase
            g_off[lane] = off
            g_spec_w[lane] = spec_w
            if lanes:  # the rest with the group's (below)
                g_da[lane] = par[P_ADARK] * (share / max(k, 1))
                g_sh2[lane] = s_hat * s_hat
                continue
            # Dark channels tied to their neighbours, by the noise's share of the rows.
            if noisy_model and par[P_ADARK] > 0.0:
                nshare = share / max(k, 1)
                for c in range(m - 1):
                    wd2 = par[P_ADARK] * nshare * dark[c] / (s_hat * s_hat)
                    qm[c, c] += wd2
                    qm[c + 1, c + 1] += wd2
                    qm[c + 1, c] -= wd2
                    if c < first[c + 1]:
                        first[c + 1] = c
            if keep_drift:  # the drift part, for re-weighting or replacing the events
                qd[:, :] = 0.0  # (read later over the final, wider envelope)
                for i in range(m):
                    qvd[i] = qv[i]
                    for j in range(first[i], i + 1):
                        qd[i, j] = qm[i, j]
            _assemble(
                False, qm, qv, qd, qvd, first, evr, evc, evlo, evhi, zz, k, spec,
                spec_first, spec_w, par,
            )  # fmt: skip
        if lanes:  # the group's systems, side by side, as the one-pixel code's
            _lane_rows(
                adrs, adlo, adhi, adc, ad_w, ad_n, nl, n_ad, rl, sw, rw, ql, qvl, fu, m
            )  # fmt: skip
            for lane in range(nl):
                for j in range(n_ad):
                    ar = adrs[lane, j]
                    for c in range(_u(adlo[lane, j]), _u(adhi[lane, j])):
                        ar[c] = 0.0
            if noisy_model and par[P_ADARK] > 0.0:
                _lane_dark(ql, fu, dark, g_da, g_sh2, nl, m)
            if keep_drift:
                _lane_copy(ql, qvl, qdl, qvdl, fu, m)
            _lane_assemble(
                False, nl, ql, qvl, qdl, qvdl, fu, evrs, evlos, evhis, evcs, zzs, g_k,
                rl, sw, rw, spec, spec_first, g_spec_w, par, split, evxs, lng,
                lzz,
            )  # fmt: skip
        # The group's pixels solved together; then each pixel's further passes.
        for lane in range(group):
            todo[lane] = lane < nl
        _solve_group(
            nl, todo, qms, qvs, firsts, xs, g_steps, ql, qvl, fu, ptr, lfl, invl, xl,
            fail, free, lf, inv, p, gr, par, max_iters, lng, lzz, evrs, evlos,
            lw,
        )  # fmt: skip
        # The photoreceptor model linearised at the answer replaces the delay-shifted
        # event rows (Gauss–Newton passes: the first for every pixel, another while
        # the pixel's last pass moved it by more than lowpass_tol).
        for lp_pass in range(lp_passes):
            col = np.nan  # the group's column offset, if all its pixels share one
            any_todo = False
            for lane in range(nl):
                todo[lane] = g_steps[lane] >= 0 and (lp_pass == 0 or lp_more[lane])
                if todo[lane]:
                    any_todo = True
                    if col != col:
                        col = g_off[lane]
                    elif g_off[lane] != col:
                        col = np.inf
            if not any_todo:
                break
            side = lane_lp and math.isfinite(col)  # four lanes side by side
            if side:
                if not col == col_done:
                    _column_grid(col, par, ipar, table, span_lo, span_hi, cspan, crow)
                    col_done = col
                for lane in range(nl):
                    if todo[lane]:
                        _clear_events(evrs[lane], evlos[lane], evhis[lane], g_k[lane])
                _lane_lowpass_rows(
                    todo, nl, xs, traws, steps2, wns, g_k, g_phase, par, ipar, cspan,
                    crow, vl, fqs, qh, apps, a_w, evrs, evcs, evlos, evhis, lpl, x4,
                    st,
                )  # fmt: skip
            for lane in range(nl):
                if not todo[lane]:
                    continue
                k = g_k[lane]
                if not side:  # one pixel at a time
                    _clear_events(evrs[lane], evlos[lane], evhis[lane], k)
                    if not g_off[lane] == col_done:
                        _column_grid(
                            g_off[lane], par, ipar, table, span_lo, span_hi, cspan,
                            crow,
                        )  # fmt: skip
                        col_done = g_off[lane]
                    _lowpass_rows(
                        xs[lane], traws[lane], steps2[lane], wns[lane], k,
                        g_phase[lane], par, ipar, cspan, crow, vv, fq, qh, apps, a_w,
                        st, evrs[lane], evcs[lane], evlos[lane], evhis[lane], lp_f,
                    )  # fmt: skip
                zz = zzs[lane]
                for i in range(k):
                    zz[i] = 1.0
                if not lanes:
                    _assemble(
                        True, qms[lane], qvs[lane], qds[lane], qvds[lane], firsts[lane],
                        evrs[lane], evcs[lane], evlos[lane], evhis[lane], zz, k, spec,
                        spec_first, g_spec_w[lane], par,
                    )  # fmt: skip
            if lanes:
                _lane_assemble(
                    True, nl, ql, qvl, qdl, qvdl, fu, evrs, evlos, evhis, evcs, zzs,
                    g_k, rl, sw, rw, spec, spec_first, g_spec_w, par, split, evxs,
                    lng, lzz,
                )  # fmt: skip
            for lane in range(nl):
                for i in range(m):
                    xprev[lane, i] = xs[lane, i]
            _solve_group(
                nl, todo, qms, qvs, firsts, xs, g_steps, ql, qvl, fu, ptr, lfl, invl,
                xl, fail, free, lf, inv, p, gr, par, max_iters, lng, lzz, evrs,
                evlos, lw,
            )  # fmt: skip
            # How far the pass moved each pixel: another pass where it moved by more
            # than lowpass_tol (||Δx||² > tol² ||x||², as _pipeline's JAX passes).
            for lane in range(nl):
                dx2 = 0.0
                x2 = 0.0
                for i in range(m):
                    d = xs[lane, i] - xprev[lane, i]
                    dx2 += d * d
                    x2 += xs[lane, i] * xs[lane, i]
                lp_more[lane] = (
                    todo[lane] and g_steps[lane] >= 0
                    and dx2 > par[P_LP_TOL] * par[P_LP_TOL] * x2
                )  # fmt: skip
        # Robust reweighting: rows far outside their noise count linearly (Huber)
        # or not at all; a pixel stops when none is far out.
        for lane in range(nl):
            todo[lane] = g_steps[lane] >= 0
        for _ in range(robust_steps):
            more = False
            for lane in range(nl):
                todo[lane] = todo[lane] and g_steps[lane] >= 0
                if not todo[lane]:
                    continue
                k = g_k[lane]
                evr = evrs[lane]
                evc = evcs[lane]
                evlo = evlos[lane]
                evhi = evhis[lane]
                zz = zzs[lane]
                for i in range(k):  # residuals in standard deviations of their rows
                    absz[i] = _row_z(evr, evc, evlo, evhi, sigmas[lane], xs[lane], i)
                med = _median(absz, k, mbuf) if k > 0 else 0.0
                scale = max(1.4826 * med, 1.0)
                any_big = False
                for i in range(k):
                    if absz[i] / scale > par[P_RC]:
                        any_big = True
                if not any_big:  # (its weights stay those its answer was solved with)
                    todo[lane] = False
                    continue
                for i in range(k):
                    a = absz[i] / scale
                    u = 1.0
                    if a > par[P_RC]:
                        u = math.sqrt(par[P_RC] / a)
                    if a > par[P_REJECT]:
                        u = 0.0
                    zz[i] = u  # the rows' weights
                more = True
                if not lanes:
                    _assemble(
                        True, qms[lane], qvs[lane], qds[lane], qvds[lane], firsts[lane],
                        evr, evc, evlo, evhi, zz, k, spec, spec_first, g_spec_w[lane],
                        par,
                    )  # fmt: skip
            if not more:
                break
            if lanes:
                _lane_assemble(
                    True, nl, ql, qvl, qdl, qvdl, fu, evrs, evlos, evhis, evcs, zzs,
                    g_k, rl, sw, rw, spec, spec_first, g_spec_w, par, split, evxs,
                    lng, lzz,
                )  # fmt: skip
            _solve_group(
                nl, todo, qms, qvs, firsts, xs, g_steps, ql, qvl, fu, ptr, lfl, invl,
                xl, fail, free, lf, inv, p, gr, par, max_iters, lng, lzz, evrs,
                evlos, lw,
            )  # fmt: skip
        # How well each answer fits its event rows (out_fit).
        for lane in range(nl):
            r = r0 + lane
            out_fit[r, 0] = np.nan
            out_fit[r, 1] = np.nan
            out_fit[r, 2] = np.nan
            if not noisy_model or g_steps[lane] < 0:
                continue
            cap = par[P_REJECT] * par[P_REJECT]
            z_max = 0.0
            i_max = -1.0
            total = 0.0
            for i in range(g_k[lane]):
                a = _row_z(
                    evrs[lane], evcs[lane], evlos[lane], evhis[lane], sigmas[lane],
                    xs[lane], i,
                )  # fmt: skip
                if a > z_max:
                    z_max = a
                    i_max = float(i)
                total += min(a * a, cap)
            out_fit[r, 0] = z_max
            out_fit[r, 1] = i_max
            out_fit[r, 2] = total
        if lanes:
            _write_lanes(
                r0, nl, g_steps, ql, qvl, fu, xs, xl, gl, out_x, out_kkt, out_steps,
                lng, lzz, evrs, evlos, p,
            )  # fmt: skip
        for lane in range(nl):
            _clear_events(evrs[lane], evlos[lane], evhis[lane], g_k[lane])  # next pixel
            if not lanes:
                _write_answer(
                    r0 + lane, g_steps[lane], qms[lane], firsts[lane], qvs[lane],
                    xs[lane], gr, out_x, out_kkt, out_steps,
                )  # fmt: skip
