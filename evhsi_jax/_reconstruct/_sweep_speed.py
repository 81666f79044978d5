"""Each sweep's mirror speed, measured from the recording it is reconstructed from.

A mirror whose speed differs from sweep to sweep (a stepper's uneven steps, the facets
of a polygon: the simulator's `sweep_rate_jitter`) runs the band over the channels
faster or slower by a factor $f_s$ in sweep $s$: the band centre is
$λ_0 + f_s βω(t + τ_x)$ at local time $t$ instead of $λ_0 + βω(t + τ_x)$. The
calibration fits one β to all the sweeps of its chart, so it cannot know the factor
of a sweep recorded later; left alone, a factor of 1.002 (the `realistic` preset's
σ) misplaces the band by ~1 nm at the red end, and one sweep of the ColorChecker
loses ~1.3° SAM at 0.2 % jitter, ~4.7° at 0.5 % (README, Real sensors, "The mirror's
speed in each sweep").

Every pixel of a sweep shares its factor, so the recording measures it. An event at
local time $t$ of a sweep with factor $f$ is where the nominal sweep has its band at
$t' = f (t + τ_x) - τ_x$ (:func:`warp_times`); with the right factor the events of
all pixels fit the model best. :func:`estimate_speeds` solves a subset of the
sweep's pixels (`SPEED_PIXELS`, spread over the image) for three factors and takes
the vertex of the parabola through their total misfit — the sum over pixels of the
fused kernel's capped sum of squared standardised residuals (a sensor without a
noise model is weighted as with `IDEAL_NOISE`); pixels that fit far worse than the
others at the nominal speed (a stray event, a scene that changed since a carried
reference) are left out first (:func:`_typical`). Each pixel keeps its first event
and its reference: leaving the first event out as a mere reference (tried) made the
photoreceptor's delay shift, which reads the level from the steps since the first,
see a level one step low, and a 10 kHz photoreceptor without mirror jitter took a
factor of 0.998 (`tcs`, calibrated). The estimate has a bias that depends on the
scene (+0.0002 to +0.0007 on `tcs`), common to the sweeps of a recording; the common
deviation is shrunk by it (:func:`shrink_common`), so a mirror without jitter keeps
factor 1.

`reconstruct(sweep_speed="auto")` measures every sweep: a recording of one sweep (a
single capture, or each sweep of `reconstruct_sweeps`) alone, one of several each in
a window with the sweep before (that one's factor fixed at its estimate; the rows
that link two sweeps are then in the fit). Until the calibration read its chart's
sweeps at their own speeds (`calibrate`, `_calibrate._chart.chart_sweep_speeds`),
`auto` left recordings of several sweeps at the calibration's speed: with a
calibration fitted to a jittery chart at one speed, the windows gained little
(`tcs`, 0.2 % jitter, 4 sweeps: 2.31° → 2.20°; the true factors gave 2.34°). With
the chart read at its sweeps' speeds they gain what the true factors do (the same
case: 4.46° → 0.87°, true factors 0.90°; README, Real sensors, "The mirror's speed
in the chart's sweeps").
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._base import use_numba
from ._fused import FusedProblem, solve_fused

#: Pixels solved per sweep and candidate factor (the most; fewer in small images).
#: 256, 512 and 1024 gave the same estimates to ~0.0002 on `tcs` (threshold noise
#: 0.01, 0.3 % jitter, four draws; a development run of an earlier version), whose
#: error was a bias of ~+0.0006.
SPEED_PIXELS = 512
#: A pixel takes part with at least this many events in the sweep.
SPEED_MIN_EVENTS = 8
#: Spacing of the three factors whose parabola gives the minimum.
SPEED_STEP = 0.002
#: The search stays within 1 ± this (the rig key `sweep_rate_jitter` is ≤ 1 %).
SPEED_BOUND = 0.03
#: Fewer pixels than this in a sweep: its factor is left at 1.
SPEED_MIN_PIXELS = 32
#: The estimate's bias that depends on the scene (the largest seen on the training
#: scene `tcs`: +0.0007 with threshold noise 0.01): a recording's common deviation
#: is shrunk by it (:func:`shrink_common`).
SPEED_BIAS = 7e-4
#: The noise model `[σ_C, σ_t, d_w]` the subsets are weighted with when the sensor
#: has none (ideal within what the calibration tells: σ_C < 0.002): rows of linear
#: intensity, as the ideal solve's, each with a σ of its own.
IDEAL_NOISE = np.array([1e-3, 0.0, 0.0])


def warp_times(t_rel, columns, offsets_us, period_us, factors):
    """Event times moved to where the nominal sweep has the band that a sweep run at
    speed `factors[s]` had: local time $t$ of sweep $s$ becomes
    $f_s (t + τ_x) - τ_x$, kept inside the sweep ([0, P)).

    `t_rel`: event times from the recording's start (sweep 0 starts at 0), `columns`:
    each event's column, `offsets_us`: τ per column, `factors`: one per sweep (events
    after the last sweep use its factor). Monotone within a pixel's sweep, so each
    pixel's events keep their order."""
    t_rel = np.asarray(t_rel, np.float64)
    factors = np.asarray(factors, np.float64)
    s = np.floor(t_rel / period_us)
    local = t_rel - s * period_us
    f = factors[np.clip(s, 0, factors.size - 1).astype(np.int64)]
    tau = np.asarray(offsets_us, np.float64)[columns]
    moved = f * (local + tau) - tau
    moved = np.clip(moved, 0.0, np.nextafter(period_us, 0.0))
    return s * period_us + moved


def warp_lists(lists, width, offsets_us, period_us, factors):
    """:func:`warp_times` on the event lists of :func:`._pixels.pixel_lists` (a new
    tuple; the lists given are not changed). Factors all 1 return the lists as
    given."""
    if np.all(np.asarray(factors) == 1.0):
        return lists
    counts, starts, t_rel, sgn = lists
    if use_numba():  # (one pass: _group_jit.warp_pixel_times)
        from ._group_jit import warp_pixel_times

        out = np.empty_like(t_rel, np.float64)
        warp_pixel_times(
            np.asarray(t_rel, np.float64), starts.astype(np.int64),
            counts.astype(np.int64), np.int64(width),
            np.asarray(offsets_us, np.float64), float(period_us),
            np.asarray(factors, np.float64), out,
        )  # fmt: skip
        return counts, starts, out, sgn
    columns = np.repeat(np.arange(counts.size) % width, counts)
    return counts, starts, warp_times(t_rel, columns, offsets_us, period_us, factors), sgn


@dataclasses.dataclass(frozen=True)
class SpeedEstimate:
    """What :func:`estimate_speeds` found, per sweep."""

    factors: np.ndarray  # (sweeps,) the factor used (1 where not estimated)
    pixels: np.ndarray  # (sweeps,) pixels solved to estimate it (0: not estimated)
    evaluations: int  # subset solves in all


def estimate_speeds(rig, table, cfg, spec, width, offsets_us, sweeps, noise, lists,
                    lead, thr_on, thr_off, period_us, *, threads=None,
                    common=None) -> SpeedEstimate:  # fmt: skip
    """Each sweep's speed factor from the recording (module docstring).

    `common`: one factor for all the sweeps, the mean of their estimates (before the
    shrinkage of :func:`shrink_common`) — for a mirror whose sweeps keep one speed.
    Default: when the rig's `sweep_rate_jitter` is 0 (what `calibrate` writes when
    the chart's sweeps agree within their estimate's error) and the recording has
    several sweeps. Each sweep's own estimate has an error of a few 1e-4 (a sensor
    without jitter, held out: background 1 Hz/px, 4 sweeps, 1.02° → 1.11° with the
    sweeps' own factors), which a steady mirror need not pay.

    `lists`: the recording's event lists (:func:`._pixels.pixel_lists`, not warped),
    `lead`: each pixel's carried reference (`_pipeline._reference_lead_us`), `noise`:
    the solve's noise model (the misfit is in units of each row's σ). The subsets
    are solved by the fused kernel with `cfg` but without the robust reweighting
    (its weights would hide what the factor changes). Pixels that fit far worse than
    the subset's typical pixel at the nominal speed (:func:`_typical`: a stray event,
    a pixel whose scene changed since its carried reference) are left out first."""
    plain = dataclasses.replace(cfg, robust_steps=0)
    probs = [
        FusedProblem(rig, table, plain, spec, width, offsets_us, n, noise)
        for n in range(1, min(sweeps, 2) + 1)
    ]  # (one sweep, and a sweep with the one before)
    eta = float(rig.refractory_us)
    counts = lists[0]
    factors = np.ones(sweeps)
    pixels = np.zeros(sweeps, np.int64)
    evaluations = 0
    pool = candidates(counts, sweeps)
    for s in range(sweeps):
        sub = _sweep_subset(lists, pool, s, period_us, eta, lead, width, offsets_us,
                            factors)  # fmt: skip
        if sub is None:
            continue
        before = factors[max(s - 1, 0) : s]  # (the sweep before, estimated)

        def misfit(f, sub=sub, before=before, per_pixel=False):
            return _misfit(probs[before.size], sub, np.append(before, f), width,
                           offsets_us, period_us, thr_on, thr_off, threads,
                           cfg.robust_reject, per_pixel)  # fmt: skip

        # (the nominal speed's misfit of the pixels kept: each pixel is solved on
        # its own, so it is their share of this solve's, not a solve of its own)
        sub, at_one = _typical(sub, misfit(1.0, per_pixel=True))
        pixels[s] = sub[0].size
        factors[s], n_eval = _minimise(lambda f, sub=sub: misfit(f, sub),
                                       known={1.0: at_one})  # fmt: skip
        evaluations += n_eval + 1
    measured = pixels > 0
    if common is None:
        common = sweeps > 1 and float(rig.effects.sweep_rate_jitter) == 0.0
    if common and measured.any():
        factors[measured] = factors[measured].mean()
    return SpeedEstimate(shrink_common(factors, measured), pixels, evaluations)


#: A subset's pixel whose misfit per event row at the nominal speed exceeds this many
#: times the subset's median is left out of the estimate (:func:`_typical`).
SPEED_OUTLIER = 5.0


def _typical(sub, chi):
    """The subset (and its total misfit `chi`, per pixel, at the nominal speed)
    without its pixels whose misfit per row `chi / rows` is more than
    `SPEED_OUTLIER` × the median: a mirror's speed moves every pixel's fit, a stray
    event or a changed scene a few. It came with the pixels' first events kept
    (module docstring), after a held-out run of the version before had lost 1.3–1.8°
    on background activity of 1 and 3 Hz (1.92° → 3.26°, 2.55° → 4.31° from one
    sweep); which of the two mended those rows was not measured apart."""
    sel, starts, counts, t, sgn, lead = sub
    per_row = chi / np.maximum(counts[sel], 1)
    keep = per_row <= SPEED_OUTLIER * np.median(per_row)
    return (sel[keep], starts, counts, t, sgn, lead), float(chi[keep].sum())


def shrink_common(factors, measured, bias=None):
    """The factors with their common part shrunk towards 1: the mean deviation `d`
    of the measured sweeps becomes `d (1 - bias² / d²)` (0 when |d| ≤ `bias`;
    default `SPEED_BIAS`), the sweeps' deviations from their mean are kept. The
    estimate has a bias that depends on the scene (model errors; ~+0.0002 to
    +0.0007 on `tcs`), the same for every sweep of a recording: their differences
    are measured well, their common level to about that bias. Without the
    shrinkage a sensor without mirror jitter took a factor of ~0.9993 (held-out
    ColorChecker, background 0.3 Hz: 0.16° lost from one sweep); with it a
    deviation well above the bias is kept nearly whole (0.002: 88 %)."""
    bias = SPEED_BIAS if bias is None else bias
    factors = np.asarray(factors, np.float64).copy()
    if not np.any(measured):
        return factors
    d = float(np.mean(factors[measured])) - 1.0
    kept = d * max(0.0, 1.0 - bias**2 / d**2) if d != 0.0 else 0.0
    factors[measured] -= d - kept
    return factors


def candidates(counts, sweeps):
    """Pixels that may take part: enough events for every sweep to give
    `SPEED_MIN_EVENTS`, at most 4 × `SPEED_PIXELS` of them spread evenly over the
    image (flat order)."""
    pix = np.flatnonzero(counts >= SPEED_MIN_EVENTS * max(1, sweeps) // 2)
    limit = 4 * SPEED_PIXELS
    if pix.size > limit:
        pix = pix[np.linspace(0, pix.size - 1, limit).round().astype(np.int64)]
    return pix


def _sweep_subset(lists, pix, s, period_us, eta, lead, width, offsets_us, factors):
    """Up to `SPEED_PIXELS` of the pixels `pix` that have enough events in sweep `s`,
    with their events of that sweep and of the one before (the window), as a
    recording of its own: `(sel, starts, counts, t, sgn, lead)`, per-pixel arrays
    over the whole image (zero outside `sel`), times from the window's start. The
    first reference of a window from sweep 0 is the recording's (`lead`: the
    baseline, or `reconstruct_sweeps`' carried reference); of a later window, the
    release after the pixel's last event before it, its time moved by its sweep's
    factor (`factors`, estimated already). Why the sweep before: a sweep's first
    event refers to the level its pixel's last event of the sweep before left, and
    the noise model gives that row the variance of a level summed over the earlier
    sweep's steps; cut at the sweep's start, that row would misfit. None when fewer
    than `SPEED_MIN_PIXELS` pixels have enough events."""
    counts, starts, t_rel, sgn = lists
    n = counts.size
    k = counts[pix]
    first = max(s - 1, 0)
    sweep_of = [np.floor(t_rel[starts[p] : starts[p] + c] / period_us) for p, c in
                zip(pix, k)]  # fmt: skip
    a = np.array([np.searchsorted(v, first, "left") for v in sweep_of], np.int64)
    m = np.array([np.searchsorted(v, s, "left") for v in sweep_of], np.int64)
    b = np.array([np.searchsorted(v, s, "right") for v in sweep_of], np.int64)
    ok = (b - m) >= SPEED_MIN_EVENTS
    if ok.sum() < SPEED_MIN_PIXELS:
        return None
    pix, a, b = pix[ok], a[ok], b[ok]
    if pix.size > SPEED_PIXELS:
        take = np.linspace(0, pix.size - 1, SPEED_PIXELS).round().astype(np.int64)
        pix, a, b = pix[take], a[take], b[take]
    use = b - a
    sub_counts = np.zeros(n, np.int64)
    sub_starts = np.zeros(n, np.int64)
    sub_counts[pix] = use
    sub_starts[pix] = np.cumsum(use) - use
    src = np.repeat(starts[pix] + a, use) + (
        np.arange(int(use.sum())) - np.repeat(np.cumsum(use) - use, use)
    )
    t = t_rel[src] - first * period_us
    sub_lead = np.array(lead, np.float64, copy=True)
    before = a > 0
    if first > 0 and before.any():
        prev = t_rel[starts[pix[before]] + a[before] - 1]
        last = warp_times(prev, pix[before] % width, offsets_us, period_us, factors) + eta
        sub_lead[pix[before]] = np.mod(np.maximum(first * period_us - last, 0.0),
                                       period_us)  # fmt: skip
    return pix, sub_starts, sub_counts, t, sgn[src], sub_lead


def _misfit(prob, sub, factors, width, offsets_us, period_us, thr_on, thr_off,
            threads, reject, per_pixel=False):  # fmt: skip
    """Total misfit of the subset's answers with its events warped by `factors` (one
    per sweep of the subset's window); per pixel with `per_pixel`."""
    sel, starts, counts, t, sgn, lead = sub
    columns = np.repeat(np.arange(counts.size) % width, counts)
    tw = warp_times(t, columns, offsets_us, period_us, factors)
    fit = np.empty((sel.size, 3))
    _, _, steps = solve_fused(prob, sel, starts, counts, tw, sgn, lead, thr_on,
                              thr_off, threads=threads, fit=fit)  # fmt: skip
    chi = fit[:, 2]
    bad = (steps < 0) | ~np.isfinite(chi)
    chi = np.where(bad, reject**2 * counts[sel], chi)
    return chi if per_pixel else float(chi.sum())


def _minimise(fun, step=SPEED_STEP, bound=SPEED_BOUND, known=None):
    """A minimum of `fun` near 1: three points `step` apart, moved downhill until the
    middle one is lowest, and the vertex of their parabola (within a step of the
    middle); 1 when the points reach 1 ± `bound` without a minimum (a misfit that
    keeps falling is another model error, not the mirror). `known`: values of `fun`
    already computed, by argument. Returns `(argmin, evaluations)` (the new ones).

    One parabola is enough: on `tcs` (threshold noise 0.01, mirror-speed jitter
    0.3 %, four draws; a development run of an earlier version) a second one through
    points half as far apart moved the answer by ≤ 0.0001, against a bias of
    ~+0.0006 that neither removes."""
    seen = {round(f, 12): v for f, v in (known or {}).items()}
    given = len(seen)

    def value(f):
        key = round(f, 12)
        if key not in seen:
            seen[key] = fun(f)
        return seen[key]

    mid = 1.0
    while True:
        lo, c, hi = value(mid - step), value(mid), value(mid + step)
        if c <= lo and c <= hi:
            break
        nxt = mid - step if lo < hi else mid + step
        if abs(nxt - 1.0) > bound:  # no minimum within the bound: not measured
            return 1.0, len(seen) - given
        mid = nxt
    curv = lo - 2.0 * c + hi
    if curv <= 0:  # (flat or concave: the middle point)
        return mid, len(seen) - given
    vertex = mid + 0.5 * step * (lo - hi) / curv
    return min(max(vertex, mid - step), mid + step), len(seen) - given
