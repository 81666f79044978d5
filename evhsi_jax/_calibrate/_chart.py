"""Gray-chart data and the per-pixel quantities measured from it.

:func:`chart_data` turns a chart capture into per-pixel event lists with the chart's
reflectance; :func:`chart_residuals` are the forward model's own equations at the
observed event times (module :mod:`._fit` explains the residual); and
:func:`threshold_maps_from_chart` gives every pixel its own ON and OFF threshold in
closed form, with the optics' blur (a Gaussian PSF searched on a grid) and stray events
accounted for.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from .._base import call_exported
from .._model import (
    BandTable,
    EventStream,
    Rig,
    Scene,
    band_overlap,
    band_table,
    lookup,
    lookup_tangents,
    photoreceptor_lowpass,
)
from .._reconstruct import group_pixels, pixel_lists, warp_lists, warp_times

__all__ = [
    "ChartData",
    "ChartSpeeds",
    "PackedEvents",
    "chart_sweep_speeds",
    "chart_data",
    "chart_log_steps",
    "chart_residuals",
    "packed_log_steps",
    "packed_scaled",
    "packed_scaled_tangents",
    "spectral_traces",
    "sweep_first_events",
    "threshold_maps_from_chart",
]


@dataclasses.dataclass(frozen=True)
class ChartData:
    """Padded event lists of chart pixels with their known reflectance (host arrays).

    `t_us`, `polarity`, `mask`: `(n, k)`; `column`, `pixel`, `spectrum`: `(n,)`;
    `spectra`: the chart's distinct reflectances `(S, F)` on the rig's fine grid
    (F = M × sub), indexed by `spectrum`; `width`: sensor width.
    """

    t_us: np.ndarray
    polarity: np.ndarray
    mask: np.ndarray
    column: np.ndarray
    pixel: np.ndarray
    spectrum: np.ndarray
    spectra: np.ndarray
    width: int

    def subset(self, index) -> ChartData:
        """The pixels `index` (rows of the per-pixel arrays)."""
        return dataclasses.replace(
            self,
            t_us=self.t_us[index],
            polarity=self.polarity[index],
            mask=self.mask[index],
            column=self.column[index],
            pixel=self.pixel[index],
            spectrum=self.spectrum[index],
        )

    @property
    def reflectance(self) -> np.ndarray:
        """Each pixel's fine reflectance, `(n, F)`."""
        return self.spectra[self.spectrum]

    @property
    def events(self) -> int:
        return int(self.mask.sum())


def chart_data(
    events: EventStream,
    chart: Scene,
    rig: Rig,
    *,
    t_start_us: int | None = None,
    rows_per_label: int | None = None,
    max_events: int = 256,
    pixels: np.ndarray | None = None,
    sweep_speeds: ChartSpeeds | None = None,
) -> ChartData:
    """Select chart pixels and pad their events into one array.

    **Arguments:**

    - `events`: the capture; `chart`: the chart scene (same size as the sensor).
    - `rig`: for the channel grid.
    - `t_start_us`: sweep phase 0 (default: first trigger, else 0).
    - `rows_per_label`: keep at most this many rows of each chart patch per column
      (evenly spread) to bound the work; `None` keeps all pixels.
    - `max_events`: at most this many events per pixel (the earliest).
    - `pixels`: `(H, W)` bool, only these pixels (with `rows_per_label`: both).
    - `sweep_speeds`: each sweep's mirror speed (:func:`chart_sweep_speeds`): the events
      are read where the nominal sweep has the band they saw
      (:func:`evhsi_jax.reconstruction.warp_times`); None reads every sweep at the
      rig's speed.
    """
    if (chart.height, chart.width) != (events.height, events.width):
        raise ValueError(
            f"the chart is {chart.height}x{chart.width} but the capture is "
            f"{events.height}x{events.width}"
        )
    if t_start_us is None:
        t_start_us = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    keep = np.ones((chart.height, chart.width), bool)
    if rows_per_label is not None:
        keep[:] = False
        for lab in np.unique(chart.labels):
            rows = np.nonzero((chart.labels == lab).any(axis=1))[0]
            pick = rows[
                np.linspace(0, rows.size - 1, min(rows_per_label, rows.size))
                .round()
                .astype(int)
            ]
            keep[pick] |= chart.labels[pick] == lab
    if pixels is not None:
        keep &= np.asarray(pixels, bool)
    pix = events.y.astype(np.int64) * events.width + events.x
    sel = keep.reshape(-1)[pix]
    sub = events.take(np.nonzero(sel)[0])
    lists = None
    if sweep_speeds is not None:
        lists = sweep_speeds.warp(pixel_lists(sub, t_start_us), events.width)
    batches, counts, _ = group_pixels(
        sub,
        t_start_us=t_start_us,
        chunk_pixels=events.width * events.height,
        min_chunk=1,
        max_events=max_events,
        lists=lists,
    )
    if not batches:
        raise ValueError("the chart capture has no events on the chart pixels")
    k = max(b.t_us.shape[1] for b in batches)
    parts = []
    for b in batches:
        v = b.pixel >= 0
        pad = ((0, 0), (0, k - b.t_us.shape[1]))
        parts.append(
            (
                np.pad(b.t_us[v], pad),
                np.pad(b.polarity[v], pad),
                np.pad(b.mask[v], pad),
                b.column[v],
                b.pixel[v],
            )
        )
    t, p, m, col, px = (np.concatenate(z) for z in zip(*parts))
    # The chart's reflectance is known finely: use it on the simulator's fine grid, so
    # reflectance slopes inside a channel (steep at the blue end of white paper) do not
    # bias the fit of the time axis.
    fine = chart.palette_on(rig.grid.fine_edges_nm)
    labels = chart.labels.reshape(-1)[px]
    used, spectrum = np.unique(labels, return_inverse=True)
    return ChartData(t, p, m, col, px, spectrum.reshape(-1), fine[used], events.width)


def sweep_first_events(data: ChartData, period_us: float) -> np.ndarray:
    """`(n, k)` bool: each pixel's first event in every sweep after its first event,
    i.e. the events whose reference $ρ = τ_{k-1} + η$ lies in an earlier sweep.

    Their model step rests on what happened to the pixel in the dark between sweeps,
    which the chart's model does not see: events there are screened out (background
    activity, a hot pixel's), yet a real comparator that fired resets its reference;
    and a slow photoreceptor is still settling from the last sweep (at 3 kHz and the
    dark level of the paper's rig its time constant is ~1.8 ms), firing OFF events
    late in the dark part that the screening also drops. One such event off by a whole
    threshold outweighs hundreds that fit (squared residuals): a 3 kHz chart of 32
    sweeps was fitted with β 0.23 % off and a threshold noise of 0.0024 the sensor
    does not have. The fit (:func:`._fit._screened_chart_data`) and the threshold
    maps (:func:`threshold_maps_from_chart`) leave these events out (~1 event in 20);
    they stay in the lists, so the next event's reference is unchanged."""
    sweep = np.floor(np.asarray(data.t_us, np.float64) / float(period_us))
    first = np.zeros(sweep.shape, bool)
    first[:, 1:] = sweep[:, 1:] != sweep[:, :-1]
    return first & data.mask


#: Chart pixels each sweep's speed is measured from (the most; spread evenly): the
#: factor is common to a sweep's pixels, and 2048 of them measure it to ~1e-5 on an
#: ideal sensor (32×48 chart).
SPEED_CHART_PIXELS = 2048
#: Spacing of the three factors whose parabolas give each sweep's (in rounds).
SPEED_CHART_STEP = 0.002
#: Rounds of parabolas at most (each around the last's answers, which moved by a step
#: at most); they stop when no factor moved by more than `SPEED_CHART_TOL`.
SPEED_CHART_ROUNDS = 8
SPEED_CHART_TOL = 2e-5
#: The factors stay within 1 ± this (the rig key `sweep_rate_jitter` is ≤ 1 %).
SPEED_CHART_BOUND = 0.03
#: Residuals beyond this (threshold units) count as this in the sweeps' misfit: a
#: stray event moves its sweep's parabola by no more than a poor fit does.
SPEED_CHART_CAP = 3.0
#: The sweeps are read at their own speeds when the factors' robust spread exceeds
#: this many times their median standard error, and `SPEED_CHART_MIN_JITTER`.
SPEED_CHART_SIGNIFICANCE = 4.0
#: (Below a relative spread of 0.01 %, a sweep's band is misplaced by < 0.05 nm.)
SPEED_CHART_MIN_JITTER = 1e-4
#: A sweep with fewer measured events keeps factor 1 (and does not count).
SPEED_CHART_MIN_EVENTS = 200


@dataclasses.dataclass(frozen=True)
class ChartSpeeds:
    """Each sweep's mirror-speed factor in a chart capture (:func:`chart_sweep_speeds`)
    and what moving its events takes.

    `factors`: `(sweeps,)`, mean 1 over the measured sweeps (their common speed is
    the rig's β); `sigma`: each factor's standard error (inf: not measured);
    `offsets_us`: the τx of the rig they were measured with, `(W,)`; `period_us`.
    """

    factors: np.ndarray
    sigma: np.ndarray
    offsets_us: np.ndarray
    period_us: float

    @property
    def measured(self) -> np.ndarray:
        return np.isfinite(self.sigma)

    @property
    def jitter(self) -> float:
        """The factors' relative spread (1.4826 × median absolute deviation: a sweep
        the estimate got wrong does not make it; the simulator's `sweep_rate_jitter`
        is their σ)."""
        f = self.factors[self.measured]
        if f.size < 3:
            return 0.0
        return float(1.4826 * np.median(np.abs(f - np.median(f))))

    @property
    def significant(self) -> bool:
        """Whether the sweeps' speeds differ by more than their estimate's error."""
        if self.measured.sum() < 3:
            return False
        noise = float(np.median(self.sigma[self.measured]))
        return self.jitter > max(SPEED_CHART_SIGNIFICANCE * noise, SPEED_CHART_MIN_JITTER)

    def warp(self, lists, width: int):
        """:func:`pixel_lists` of the capture (times from its start) with every event
        moved to where the nominal sweep has its band."""
        return warp_lists(lists, width, self.offsets_us, self.period_us, self.factors)

    def columns(self, x0: int, x1: int) -> ChartSpeeds:
        """The same factors for a crop of the sensor's columns `x0:x1`."""
        return dataclasses.replace(self, offsets_us=self.offsets_us[x0:x1])


def _padded_lists(d: ChartData) -> ChartData:
    """`d` with its event slots padded to a power of two (at least 8, masked): the
    log steps' programs then see few shapes across bands of rows and captures."""
    k = max(8, 1 << int(d.t_us.shape[1] - 1).bit_length())
    pad = ((0, 0), (0, k - d.t_us.shape[1]))
    return dataclasses.replace(
        d, t_us=np.pad(d.t_us, pad), polarity=np.pad(d.polarity, pad),
        mask=np.pad(d.mask, pad),
    )  # fmt: skip


def chart_sweep_speeds(
    events: EventStream,
    chart: Scene,
    rig: Rig,
    *,
    t_start_us: int,
    rows_per_label: int | None = 4,
) -> ChartSpeeds | None:
    """Each sweep's mirror-speed factor in a chart capture, measured with a fitted rig.

    A mirror whose speed differs from sweep to sweep (`sweep_rate_jitter`) runs the
    band over the channels faster or slower by a factor $f_s$ in sweep $s$; a fit of
    one β to all the chart's sweeps takes their mean, and every event of a faster or
    slower sweep then misfits by a step that grows along the sweep — which the
    per-pixel thresholds, the noise measured and τx absorb in part. The chart's
    reflectance is known, so each sweep's factor is where its events fit the rig
    best: with the pixels' own thresholds fixed (closed form at $f = 1$), the capped
    sum of squared residuals of each sweep (:func:`_own_residuals`, capped at
    `SPEED_CHART_CAP`) at three factors `SPEED_CHART_STEP` apart, the vertex of each
    sweep's parabola (a step at most), in rounds around the last round's answers
    until they stop moving (`SPEED_CHART_ROUNDS`, `SPEED_CHART_TOL`). Up to
    `SPEED_CHART_PIXELS` chart pixels, up to `MAP_MAX_EVENTS` events each; each
    sweep's first event is left out (:func:`sweep_first_events`).

    The factors are scaled to mean 1 over the measured sweeps (β is their common
    speed). Each one's standard error is the parabola's: $σ_f^2 = 2 δ^2 S / (n
    κ)$, $S$ the sweep's misfit at its factor, $n$ its events, $κ$ the second
    difference over steps $δ$. None when the capture has fewer than three sweeps
    with `SPEED_CHART_MIN_EVENTS` events.
    """
    period = float(rig.period_us)
    w = events.width
    rig = _with_column_offsets(rig, w)
    data = chart_data(events, chart, rig, t_start_us=t_start_us,
                      rows_per_label=rows_per_label, max_events=MAP_MAX_EVENTS)  # fmt: skip
    n_px = data.t_us.shape[0]
    if n_px > SPEED_CHART_PIXELS:
        data = data.subset(
            np.linspace(0, n_px - 1, SPEED_CHART_PIXELS).round().astype(np.int64)
        )
    data = _padded_lists(data)
    data = dataclasses.replace(data, mask=data.mask & ~sweep_first_events(data, period))
    t = np.asarray(data.t_us, np.float64)
    sweep = np.floor(t / period).astype(np.int64)
    on = data.mask & (sweep >= 0)
    if not on.any():
        return None
    n_sweeps = int(sweep[on].max()) + 1
    n_ev = np.bincount(sweep[on], minlength=n_sweeps)
    measured = n_ev >= SPEED_CHART_MIN_EVENTS
    if measured.sum() < 3:
        return None
    offsets = np.asarray(rig.column_offsets_us, np.float64)
    columns = np.broadcast_to(data.column[:, None], t.shape).reshape(-1)
    overlap = band_overlap(rig)
    at_one = _log_steps(rig, data, overlap=overlap)  # (the recorded times)
    c_on, c_off = _closed_form_thresholds(at_one, data)

    def misfit(factors):  # (sweeps,) each sweep's capped sum of squared residuals
        if np.all(factors == 1.0):  # (the first round's middle: the steps above)
            steps = at_one
        else:
            moved = warp_times(t.reshape(-1), columns, offsets, period, factors)
            view = dataclasses.replace(data, t_us=moved.reshape(t.shape))
            steps = _log_steps(rig, view, overlap=overlap)
        r = _own_residuals(steps, data, c_on, c_off)
        ok = on & np.isfinite(r)
        sq = np.minimum(r[ok] ** 2, SPEED_CHART_CAP**2)
        return np.bincount(sweep[ok], sq, minlength=n_sweeps)[:n_sweeps]

    step = SPEED_CHART_STEP
    factors = np.ones(n_sweeps)
    for _ in range(SPEED_CHART_ROUNDS):
        lo, mid, hi = (misfit(factors + j * step) for j in (-1, 0, 1))
        curv = lo - 2.0 * mid + hi
        good = measured & (curv > 0)
        move = np.zeros(n_sweeps)
        move[good] = 0.5 * step * (lo[good] - hi[good]) / curv[good]
        move = np.clip(move, -step, step)  # (a step at most: then around the new ones)
        factors = np.clip(factors + move, 1.0 - SPEED_CHART_BOUND, 1.0 + SPEED_CHART_BOUND)
        sigma = np.full(n_sweeps, np.inf)
        sigma[good] = np.sqrt(2.0 * step**2 * mid[good] / (n_ev[good] * curv[good]))
        if np.abs(move).max() < SPEED_CHART_TOL:
            break
    factors[~np.isfinite(sigma)] = 1.0
    factors[np.isfinite(sigma)] /= factors[np.isfinite(sigma)].mean()
    return ChartSpeeds(factors, sigma, offsets, period)


def spectral_traces(
    rig: Rig, spectra, overlap: BandTable | None = None, product=None
) -> BandTable:
    """Intensity above c of each chart spectrum vs band centre: `(n_λ, S)` table.

    The chart's few spectra are known, so their traces over λc are tabulated once (the
    fine band table times each fine reflectance); a residual then needs a 1-D
    interpolation instead of a 360-wide dot product. Differentiable in the rig's FWHM,
    D and E through the band table. `overlap`: the rig's :func:`band_overlap`, when the
    caller keeps the band fixed and has it already (the joint fit: it is most of the
    cost otherwise); then D and E are still differentiable, the FWHM is not.
    `product`: instead of the table, a function `W ↦ overlap @ W` (`W`: `(F, C)`)
    — the fit of a band profile (`sampled_profile_product`), which never forms the
    table; `overlap` then only gives the λc grid (`lo_nm`, `step_nm`).
    """
    if overlap is None:
        table = band_table(rig)
        return BandTable(
            table.values @ jnp.asarray(spectra, table.values.dtype).T,
            table.lo_nm,
            table.step_nm,
        )
    weight = rig.camera_response * rig.lamp
    weighted = weight[:, None] * jnp.asarray(spectra, weight.dtype).T
    if product is None:
        level, traces = overlap.values @ weight, overlap.values @ weighted
    else:  # (one product for both)
        both = product(jnp.concatenate([weight[:, None], weighted], axis=1))
        level, traces = both[:, 0], both[:, 1:]
    gain = 1.0 / jnp.max(level)
    return BandTable(gain * traces, overlap.lo_nm, overlap.step_nm)


def chart_log_steps(rig: Rig, data, traces=None, filtered=None):
    """Model log steps of every chart event, shape `(n, k)` (0 in padding).

    `data` is a :class:`ChartData`, or the tuple `(t, polarity, mask, column,
    spectrum)` of JAX arrays (then `traces` is required). Differentiable in the rig.
    `filtered`: the traces through the rig's photoreceptor low-pass
    (:func:`lowpassed_traces`), when the caller has them already (a fit over blocks of
    pixels computes them once per evaluation, not once per block).
    """
    if isinstance(data, ChartData):
        traces = traces if traces is not None else spectral_traces(rig, data.spectra)
        data = _device(data, rig.fwhm_nm.dtype)
    elif traces is None:
        raise ValueError("pass the spectral traces with device arrays")
    t, _, m, col, s_idx = data
    # References: the recording start for the first event, then τ_{k-1} + η.
    t_ref = jnp.concatenate(
        [jnp.zeros_like(t[:, :1]), t[:, :-1] + rig.refractory_us], axis=1
    )
    return _log_steps_at(rig, t, t_ref, m, col[:, None], s_idx[:, None], traces, filtered)


def _log_steps_at(rig: Rig, t, t_ref, m, col, s_idx, traces, filtered):
    """Model log steps from the references `t_ref` to the events `t` (0 where `m`
    is False); `col` and `s_idx` (each event's sensor column and chart spectrum)
    broadcast against `t`."""
    offsets = rig.column_offsets(_width(rig, col))[col]
    lowpass = rig.effects.photoreceptor_hz > 0
    if lowpass:  # a known photoreceptor low-pass: the events see the filtered level
        traces = filtered if filtered is not None else lowpassed_traces(rig, traces)

    def level(tt):
        # Only each pixel's own chart spectrum is interpolated: the linearisation
        # that Levenberg–Marquardt keeps then holds (n, k) arrays, not (n, k, S).
        a = lookup(traces, rig.band_centre_nm(tt, offsets), order=3, column=s_idx)
        return _level(a, rig.baseline_level, lowpass)

    return jnp.where(m, level(t) - level(t_ref), 0.0)


def _level(a, base, lowpass: bool):
    """The log level seen at a trace value `a`: the filtered traces are log levels
    already; the unfiltered ones are intensities (`base`: the rig's baseline level)."""
    return a if lowpass else jnp.log(jnp.maximum(a, 0.0) + base)


def lowpassed_traces(rig: Rig, traces: BandTable, cutoff_hz=None) -> BandTable:
    """The chart spectra's log-intensity traces through the photoreceptor low-pass
    (:func:`evhsi_jax.forward.photoreceptor_lowpass`), tabulated over λc like the
    traces: time and λc are proportional along the sweep (one table step is
    `step / (βω)` µs), so the filter runs along the table. Exact for the chart (its
    spectra are known); differentiable in the rig. `cutoff_hz`: the cut-off, when
    it is not the rig's (static) one — a traced value while the calibration fits
    it."""
    speed = rig.band_speed_nm_per_us
    inten = jnp.maximum(traces.values, 0.0) + rig.baseline_rel
    filt = photoreceptor_lowpass(
        jnp.log(inten + rig.log_eps),
        traces.step_nm / speed,
        rig.effects.photoreceptor_hz if cutoff_hz is None else cutoff_hz,
        rig.log_eps,
        sequential=True,  # compiles faster (the fit differentiates it)
    )
    return BandTable(filt, traces.lo_nm, traces.step_nm)


def _row_totals(x, _rows):
    """Each row's sum, `(n, 1)`: the pixels of the `(n, k)` event lists are rows."""
    return jnp.sum(x, 1, keepdims=True)


def _pixel_totals(x, pixel):
    """Each event's pixel's sum over its events, at every event: the events of a
    packed block (:class:`PackedEvents`), `pixel` their pixel's index in it."""
    n = x.shape[-1]  # (a block holds at most one pixel per event)
    return jax.ops.segment_sum(x, pixel, num_segments=n, indices_are_sorted=True)[pixel]


def _least_squares_ratio(num, den):
    """`(num / den, 1 / den)`, both 0 where `den` is not positive (no events, or all
    with d = 0)."""
    ok = den > 0
    den = jnp.where(ok, den, 1.0)
    return jnp.where(ok, num / den, 0.0), jnp.where(ok, 1.0 / den, 0.0)


def _inverse_threshold_sums(d, pos, neg, totals=_row_totals, pixel=None):
    """Per pixel: the least-squares 1/C of its ON events (`pos`, 0/1) and of its OFF
    events (`neg`), with 1/Σd² and the sign (1/C and 1/Σd² are 0 where the pixel has
    no such events or they all have d = 0); `totals(x, pixel)` sums `x` over each
    pixel's events (`(n, 1)` for the rows of event lists, or at every event)."""
    sums = []
    for sel, sign in ((pos, 1.0), (neg, -1.0)):
        num = sign * totals(sel * d, pixel)
        u, inv_den = _least_squares_ratio(num, totals(sel * d * d, pixel))
        sums.append((u, inv_den, sign))
    return sums


@jax.custom_jvp
def _own_inverse_thresholds(d, pos, neg):
    """Each event's pixel's least-squares 1/C for its polarity, `(n, k)`."""
    (up, _, _), (un, _, _) = _inverse_threshold_sums(d, pos, neg)
    return pos * up + neg * un


@_own_inverse_thresholds.defjvp
def _own_inverse_thresholds_jvp(primals, tangents):
    # Written out (u = a/b, du = (da - u db)/b with a = ±Σd, b = Σd²): the automatic
    # derivative of the sums above, vmapped over the calibration's tangents, cost
    # ~2.5× the whole non-profiled normal-equations pass.
    d, pos, neg = primals
    dd = tangents[0]
    out, tan = 0.0, 0.0
    sums = _inverse_threshold_sums(d, pos, neg)
    for (u, inv_den, sign), sel in zip(sums, (pos, neg), strict=True):
        da = sign * jnp.sum(sel * dd, 1, keepdims=True)
        db = 2.0 * jnp.sum(sel * d * dd, 1, keepdims=True)
        out = out + sel * u
        tan = tan + sel * ((da - u * db) * inv_den)
    return out, tan


def chart_residuals(
    rig: Rig,
    data,
    traces=None,
    *,
    per_pixel: bool | Bool[Array, ""] = False,
    filtered=None,
):
    """Event residuals in threshold units, shape `(n, k)` (0 in padding).

    $r_k = d_k / C - σ_k$ with $d_k$ the model log step (:func:`chart_log_steps`): 0
    when the model explains event k exactly. Dividing by C (rather than residuals
    $d_k - σ_kC$ in log units) matters: in log units a rig with huge constant light
    and tiny thresholds would explain any events with tiny residuals; in threshold
    units the observed, geometric spacing of event levels rules it out.

    With `per_pixel`, each pixel's own ON and OFF thresholds are profiled out:
    $1/C_p = \\sum σ_k d_k / \\sum d_k^2$ over the pixel's events of one polarity
    (the least-squares value), so threshold mismatch cannot bias the other parameters.
    `per_pixel` may also be a boolean array (traced): then one program serves both
    (the calibration's two Levenberg–Marquardt stages are one compiled program).
    """
    d = chart_log_steps(rig, data, traces, filtered)
    pol = data.polarity if isinstance(data, ChartData) else data[1]
    mask = data.mask if isinstance(data, ChartData) else data[2]
    pol = jnp.asarray(pol).astype(d.dtype)
    pos = jnp.asarray(mask) & (pol > 0)
    neg = jnp.asarray(mask) & (pol < 0)

    def own():
        return _own_inverse_thresholds(d, pos.astype(d.dtype), neg.astype(d.dtype))

    return _scaled_residuals(rig, d, pol, pos, neg, own, per_pixel)


def _scaled_residuals(rig: Rig, d, pol, pos, neg, own, per_pixel):
    """`d·(1/C) − σ` at the events (`pos | neg`; else 0): 1/C each pixel's own
    (`own()`) or the rig's pair, chosen by `per_pixel` (a bool or a traced one)."""

    def common():
        return jnp.where(pol > 0, 1.0 / rig.threshold_on, 1.0 / rig.threshold_off)

    if isinstance(per_pixel, (bool, np.bool_)):
        u = own() if per_pixel else common()
    else:
        u = jnp.where(per_pixel, own(), common())
    return jnp.where(pos | neg, d * u - pol, 0.0)


class PackedEvents(NamedTuple):
    """A block of chart events packed one after another, pixel after pixel (each
    pixel's events in time order, its padding slots up to its last event kept, so
    that every event's reference is the time in the slot before it): the calibration
    fit's layout (:mod:`._fit`), where one program shape serves pixels of any event
    count. Every field has the block's shape `(E,)` (or `(n_blocks, E)` stacked);
    padding: `mask` False."""

    t: Any  # event times (µs)
    first: Any  # a pixel's first slot: its reference is the recording start
    polarity: Any
    mask: Any
    column: Any  # sensor column
    spectrum: Any  # chart spectrum index
    pixel: Any  # the pixel's index in the block (non-decreasing along it)


def packed_log_steps(rig: Rig, block: PackedEvents, traces, filtered=None):
    """:func:`chart_log_steps` of a packed block of events, `(E,)`."""
    t_ref = _packed_references(block, rig.refractory_us)
    return _log_steps_at(
        rig, block.t, t_ref, block.mask, block.column, block.spectrum, traces, filtered
    )


def _packed_references(block: PackedEvents, refractory_us):
    """Each packed event's reference time: the recording start for a pixel's first
    event, else the slot before's time plus the refractory period."""
    t = block.t
    t_prev = jnp.concatenate([jnp.zeros_like(t[..., :1]), t[..., :-1]], axis=-1)
    return jnp.where(block.first, jnp.zeros_like(t), t_prev + refractory_us)


def packed_log_step_tangents(rig_at, u, tans, block: PackedEvents, traces, offsets):
    """:func:`packed_log_steps` of `rig_at(u)` (`rig_at`: parameters → rig) and its
    tangents along the rows of `tans` (`(T, P)`), all at once: `(d, dd)`, `(E,)` and
    `(T, E)`.

    `traces`: the table the events read (the low-passed traces when the rig has a
    photoreceptor cut-off, else the traces), and `offsets` (`(W, 1 + T)`) the column
    offsets, each with a trailing axis of 1 + T: the value at `u`, then its tangents.
    The same numbers as `jax.jvp` of :func:`packed_log_steps` along each row, but the
    table is read once per event for all the tangents (:func:`lookup_tangents`) and
    the rest is elementwise: JAX's own derivative, mapped over the tangents, read it
    again per tangent, 16× the cost of the log steps themselves on a 48×1280 chart
    (2026-12-08).
    """
    lowpass = rig_at(u).effects.photoreceptor_hz > 0
    off = offsets[block.column]  # (E, 1 + T)

    def geometry(u, off):  # the events' and their references' band centres, the base
        rig = rig_at(u)
        t_ref = _packed_references(block, rig.refractory_us)
        base = rig.baseline_level
        return rig.band_centre_nm(block.t, off), rig.band_centre_nm(t_ref, off), base

    primal, lin = jax.linearize(geometry, u, off[:, 0])
    tangents = jax.vmap(lin)(tans, off[:, 1:].T)
    (c_t, c_ref, base), (dc_t, dc_ref, d_base) = primal, tangents
    levels = []
    for c, dc in ((c_t, dc_t), (c_ref, dc_ref)):
        a, da = lookup_tangents(traces, c, dc, column=block.spectrum, order=3)
        lv, lv_lin = jax.linearize(lambda a, b: _level(a, b, lowpass), a, base)
        levels.append((lv, jax.vmap(lv_lin)(da, d_base)))
    (l_t, dl_t), (l_ref, dl_ref) = levels
    m = block.mask
    return jnp.where(m, l_t - l_ref, 0.0), jnp.where(m, dl_t - dl_ref, 0.0)


def packed_scaled(rig: Rig, block: PackedEvents, d, per_pixel=False):
    """A packed block's residuals from its log steps `d` (:func:`packed_log_steps`):
    :func:`chart_residuals`' last part, the per-pixel sums of `per_pixel` by segments.
    Apart from `d`, it depends on the rig's thresholds only
    (:func:`packed_scaled_tangents` gives its tangents; the automatic derivative of
    this function is what tests check them against)."""
    pol = jnp.asarray(block.polarity).astype(d.dtype)
    pos = block.mask & (pol > 0)
    neg = block.mask & (pol < 0)

    def own():
        on, off = pos.astype(d.dtype), neg.astype(d.dtype)
        sums = _inverse_threshold_sums(d, on, off, _pixel_totals, block.pixel)
        return on * sums[0][0] + off * sums[1][0]

    return _scaled_residuals(rig, d, pol, pos, neg, own, per_pixel)


def packed_scaled_tangents(block: PackedEvents, d, dd, inv, d_inv, per_pixel=False):
    """:func:`packed_scaled` and its tangents, all at once: `(r, dr)`, `(E,)` and
    `(T, E)`, for the log steps `d` with tangents `dd` (`(T, E)`) and the rig's
    inverse thresholds `inv` = (1/C_on, 1/C_off) with tangents `d_inv` (`(T, 2)`).

    :func:`_own_inverse_thresholds`' rule written out for T tangents together: all
    the per-pixel, per-polarity sums of all the tangents are one segment sum of a
    `(E, 2T + 2)` array. (XLA's CPU scatter costs ~0.1 µs per index whatever the
    width of its rows: the rule mapped over the calibration's tangents, a segment
    sum per tangent, made a 24×32 chart's normal equations 2-3× slower.)"""
    dtype = d.dtype
    pol = jnp.asarray(block.polarity).astype(dtype)
    live = block.mask & (pol != 0)
    u_c = jnp.where(pol > 0, inv[0], inv[1])
    du_c = jnp.where(pol > 0, d_inv[:, :1], d_inv[:, 1:])

    def own():
        t = dd.shape[0]
        m = live.astype(dtype)
        sign = jnp.where(pol > 0, 1.0, -1.0).astype(dtype)
        # Each pixel's ON and OFF events are two segments.
        seg = 2 * block.pixel + (pol < 0).astype(block.pixel.dtype)
        x = jnp.concatenate(
            [jnp.stack([m * d, m * d * d], 1), (m * dd).T, (m * d * dd).T], axis=1
        )
        tot = jax.ops.segment_sum(x, seg, num_segments=2 * d.shape[-1])[seg]
        # (of the event's pixel and polarity)
        u, inv_den = _least_squares_ratio(sign * tot[:, 0], tot[:, 1])
        da = sign * tot[:, 2 : 2 + t].T  # (T, E)
        db = 2.0 * tot[:, 2 + t :].T
        return m * u, m * ((da - u * db) * inv_den)

    if isinstance(per_pixel, (bool, np.bool_)):
        u, du = own() if per_pixel else (u_c, du_c)
    else:
        u_o, du_o = own()
        u, du = jnp.where(per_pixel, u_o, u_c), jnp.where(per_pixel, du_o, du_c)
    r = jnp.where(live, d * u - pol, 0.0)
    dr = jnp.where(live, dd * u + d * du, 0.0)
    return r, dr


def _with_column_offsets(rig: Rig, width: int) -> Rig:
    """`rig` with its column offsets explicit (one per column)."""
    if rig.column_offsets_us is not None:
        return rig
    return rig.with_leaves(column_offsets_us=rig.column_offsets(width))


def _width(rig, col):
    if rig.column_offsets_us is None:
        raise ValueError("calibration needs explicit column offsets (one per column)")
    return rig.column_offsets_us.shape[0]


def _host_lists(d: ChartData, dtype):
    """The event lists as the model's passes take them, `(t, polarity, mask,
    column, spectrum)`, host arrays (times in `dtype`, polarity int32)."""
    return (
        np.asarray(d.t_us, dtype),
        np.asarray(d.polarity, np.int32),
        np.asarray(d.mask),
        np.asarray(d.column),
        np.asarray(d.spectrum),
    )


def _device(d: ChartData, dtype):
    """:func:`_host_lists` as JAX arrays."""
    return tuple(jnp.asarray(a) for a in _host_lists(d, dtype))


_log_steps_jit = eqx.filter_jit(chart_log_steps)


#: The photoreceptor cut-off (Hz) that the chart programs' rigs carry as their static
#: value whenever the sensor has a low-pass: the actual cut-off enters as an input
#: (:func:`lowpassed_traces`' `cutoff_hz`), so a calibrated or fitted cut-off does
#: not make every program a new compilation.
PHOTORECEPTOR_REF_HZ = 10000.0


def with_reference_cutoff(rig: Rig) -> Rig:
    """`rig` with the static cut-off `PHOTORECEPTOR_REF_HZ` (it must have one)."""
    if rig.effects.photoreceptor_hz == PHOTORECEPTOR_REF_HZ:
        return rig
    return rig.replace_host(photoreceptor_hz=PHOTORECEPTOR_REF_HZ)


def without_band_profile(rig: Rig) -> Rig:
    """`rig` without its band profile, for a program that sees the band only through
    tables made outside it (the chart's spectral traces, the band's overlap): the
    profile is a static value of the rig, part of a program's key, so a program
    given it would be compiled again for every calibration's newly fitted band."""
    return rig if rig.band_profile is None else rig.with_band_profile(None)


@eqx.filter_jit
def _lowpassed_values(rig: Rig, traces: BandTable, cutoff_hz):
    """:func:`lowpassed_traces`' values, one program for every block of a pass."""
    return lowpassed_traces(rig, traces, cutoff_hz).values


#: :func:`_log_steps` pads the chart's distinct spectra to at least this many (and to
#: a power of two): a blurred chart's band of rows has ~4–32 distinct levels, and
#: with the photoreceptor each count was a compilation of ~0.8 s on 2 cores.
MIN_SPECTRA = 32


def _log_steps(rig: Rig, data: ChartData, block_events: int = 1 << 20, overlap=None):
    """Model log steps of every chart event in blocks of pixels, `(n, k)` (host):
    :func:`_log_steps_begin` then :func:`_log_steps_end`."""
    return _log_steps_end(_log_steps_begin(rig, data, block_events, overlap))


def _log_steps_end(pending) -> np.ndarray:
    """The host array of a :func:`_log_steps_begin` (waits for its blocks)."""
    return np.concatenate([np.asarray(a, np.float64)[:rows] for a, rows in pending])


def _log_steps_begin(
    rig: Rig, data: ChartData, block_events: int = 1 << 20, overlap=None
):
    """Start the model log steps of every chart event in blocks of pixels: the
    blocks' device results with their valid rows, for :func:`_log_steps_end` (JAX
    computes them while the caller's Python goes on).

    Blocks of about `block_events` padded events, each padded to the same number of
    pixels (masked), so one compilation serves all; a smaller set of pixels is padded
    to a power of two of them, and the spectra to `MIN_SPECTRA` or a power of two,
    so the compiled shapes stay few across calls (the fit's and the maps' passes
    share them). `overlap`: the rig's :func:`band_overlap`, when the caller has it
    (a pass over many charts or bands of rows with one rig: for a sampled band
    profile it is a ~0.1 s table, and the maps' passes had made it ~20 times).
    """
    n_spec = data.spectra.shape[0]
    pad_spec = max(MIN_SPECTRA, 1 << max(n_spec - 1, 1).bit_length()) - n_spec
    data = dataclasses.replace(
        data, spectra=np.pad(data.spectra, ((0, pad_spec), (0, 0)))
    )
    traces = spectral_traces(rig, data.spectra, overlap)
    rig = without_band_profile(rig)  # (the band is in the traces)
    filtered = None
    hz = rig.effects.photoreceptor_hz
    if hz > 0:
        # Once per pass, not inside every block's program: the low-pass's scan made
        # each block shape a compilation of ~0.8 s (~0.15 s without it). The cut-off
        # is an input, and the blocks see the reference one (only its sign matters
        # to them): a fitted value compiles nothing new.
        rig = with_reference_cutoff(rig)
        args = (rig, traces, jnp.asarray(hz, rig.fwhm_nm.dtype))
        values = call_exported("chart_lowpassed", _lowpassed_values, args)
        filtered = BandTable(values, traces.lo_nm, traces.step_nm)
    dtype = rig.fwhm_nm.dtype
    n = data.t_us.shape[0]
    block = min(
        max(1, block_events // max(data.t_us.shape[1], 1)),
        1 << max(n - 1, 0).bit_length(),
    )
    out = []
    for c0 in range(0, n, block):
        part = data.subset(slice(c0, c0 + block))
        pad = block - part.t_us.shape[0]
        if pad:
            part = dataclasses.replace(
                part,
                **{
                    k: np.pad(
                        getattr(part, k),
                        ((0, pad),) + ((0, 0),) * (getattr(part, k).ndim - 1),
                    )
                    for k in ("t_us", "polarity", "mask", "column", "pixel", "spectrum")
                },
            )
        # (host arrays: the program's inputs as they are, no eager conversions)
        args = (rig, _host_lists(part, dtype), traces, filtered)
        out.append((call_exported("chart_log_steps", _log_steps_jit, args), block - pad))
    return out


PSF_GRID_PX = (0.0, 0.25, 0.4, 0.5, 0.6, 0.75, 1.0, 1.5)  # blur σ searched, pixels
STRAY_FLOOR = 0.5  # threshold units: the least residual of a stray event
MAP_MAX_EVENTS = 4096  # events per pixel the maps use (a chart recorded for ~2 s)
MAP_BLOCK_EVENTS = 1 << 21  # events per band of sensor rows in the maps' passes


def _own_residuals(steps, data: ChartData, c_on, c_off) -> np.ndarray:
    """Residuals (threshold units) with each pixel's own thresholds, `(n, k)`; NaN in
    padding and where the pixel has no threshold of the event's polarity."""
    c_px = np.where(data.polarity > 0, c_on[:, None], c_off[:, None])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(data.mask, steps / c_px - data.polarity, np.nan)


def _rms_own_thresholds(steps, data: ChartData, c_on, c_off) -> np.ndarray:
    """Per-pixel RMS residual (threshold units) with the pixel's own thresholds."""
    r = _own_residuals(steps, data, c_on, c_off)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.nanmean(r**2, axis=1))


def _robust_spread(steps, data: ChartData, c_on, c_off) -> np.ndarray:
    """Per-pixel robust spread of the residuals with the pixel's own thresholds
    (1.4826 × median |r|, threshold units): a pixel off the model everywhere (dirt,
    a defect) stands out; one with a few stray events does not."""
    r = np.abs(_own_residuals(steps, data, c_on, c_off))
    out = np.full(r.shape[0], np.nan)
    has = data.mask.any(axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: no thresholds
        out[has] = 1.4826 * np.nanmedian(r[has], axis=1)
    return out


def _closed_form_thresholds(steps: np.ndarray, data: ChartData):
    """Per-pixel C_on, C_off from model log steps: the least-squares values of the
    threshold-unit residuals, $C = \\sum d_k^2 / \\sum σ_k d_k$ (NaN where a pixel has
    no event of that polarity).

    With per-crossing noise ($d_k = C + ε_k$) this exceeds the mean step by about
    $σ_C^2/C$, and the crossings the sweep's peak cuts off pull the mean step itself
    below C. The plain mean step was tried (realistic preset, 32-sweep chart, three
    sensors): 0.1–0.25 dB lower PSNR on the held-out scene in five of six cases, so
    this estimator stays.
    """
    pos = data.mask & (data.polarity > 0)
    neg = data.mask & (data.polarity < 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        c_on = (steps**2 * pos).sum(1) / (steps * pos).sum(1)
        c_off = (steps**2 * neg).sum(1) / (-steps * neg).sum(1)
    c_on[~(c_on > 0) | (pos.sum(1) == 0)] = np.nan
    c_off[~(c_off > 0) | (neg.sum(1) == 0)] = np.nan
    return c_on, c_off


def threshold_maps_from_chart(
    events: EventStream,
    chart: Scene,
    rig: Rig,
    *,
    t_start_us: int | None = None,
    psf_sigmas_px=PSF_GRID_PX,
    return_psf: bool = False,
    sweep_speeds: ChartSpeeds | None = None,
):
    """Per-pixel ON/OFF thresholds with the global parameters fixed (closed form).

    Each event's model log step $d_k = \\log I(τ_k) - \\log I(ρ_k)$ is computed from the
    known reflectance; a pixel's $C_{on}$ and $C_{off}$ are the least-squares solutions
    of its ON and OFF residuals in threshold units (:func:`_closed_form_thresholds`),
    from up to `MAP_MAX_EVENTS` events per pixel; the pixels are processed a band of
    sensor rows at a time (`MAP_BLOCK_EVENTS` events), so memory is bounded by the band.

    **The optics' blur.** On a patch border the lens mixes two grays; a pixel there
    sees a level the chart's labels do not give, and its closed-form thresholds absorb
    the difference (per-crossing threshold noise hides the misfit in its own
    residual). The chart is therefore seen through a Gaussian PSF whose σ is chosen
    from `psf_sigmas_px` by the total squared residual of all pixels with their own
    thresholds: pooled over every border pixel, the blur is well determined although
    no single pixel shows it. `psf_sigmas_px=(0.0,)` turns this off.

    A pixel whose RMS residual with its own thresholds is still an outlier (> 2× the
    median and > median + 8 robust σ) does not follow the chart's model (dirt, a
    defect) and gets the rig's global pair, as do pixels without ON (OFF) events.
    Each sweep's first event (after the pixel's first) is kept in the lists but
    estimates nothing: its reference lies across the dark part between sweeps
    (:func:`sweep_first_events`).

    `sweep_speeds`: each sweep's mirror speed (:func:`chart_sweep_speeds`; None: the rig's
    for every sweep).

    **Returns:** `(threshold_on, threshold_off)` maps, each `(H, W)`; with
    `return_psf` also the chosen σ (pixels).
    """
    h, w = events.height, events.width
    rig = _with_column_offsets(rig, w)
    on = np.full(h * w, float(rig.threshold_on))
    off = np.full(h * w, float(rig.threshold_off))
    seen_charts = [chart.blurred(float(v)) for v in psf_sigmas_px]
    bands = _row_bands(events, MAP_BLOCK_EVENTS)
    overlap = band_overlap(rig)  # (one rig for every pass)

    last: list = []  # the latest band's lists: pass 2 starts with pass 1's last band

    def band_data(y0, y1):
        if last and last[0] == (y0, y1):
            return last[1]
        rows = np.zeros((h, w), bool)
        rows[y0:y1] = True
        try:
            d = chart_data(events, chart, rig, t_start_us=t_start_us,
                           rows_per_label=None, max_events=MAP_MAX_EVENTS,
                           pixels=rows, sweep_speeds=sweep_speeds)  # fmt: skip
        except ValueError:  # no events in these rows
            d = None
        else:
            d = _padded_lists(d)
        last[:] = [(y0, y1), d]
        return d

    period = float(rig.period_us)

    def judged(d, first=None):  # the events a threshold is estimated from
        first = sweep_first_events(d, period) if first is None else first
        return dataclasses.replace(d, mask=d.mask & ~first)

    # Pass 1: the blur, by the total squared residual over all pixels; the pixels are
    # taken a band of sensor rows at a time, so memory is bounded by the band. The
    # next blur's log steps are computed while the host reduces this one's.
    ssr = np.zeros(len(psf_sigmas_px))
    if len(psf_sigmas_px) > 1:
        for y0, y1 in bands:
            d = band_data(y0, y1)
            if d is None:
                continue
            views = [_seen_through(d, seen, rig) for seen in seen_charts]
            first = sweep_first_events(d, period)  # (the views share d's times)
            nxt = _log_steps_begin(rig, views[0], overlap=overlap)
            for i, view in enumerate(views):
                pending = nxt
                if i + 1 < len(views):
                    nxt = _log_steps_begin(rig, views[i + 1], overlap=overlap)
                steps = _log_steps_end(pending)
                view = judged(view, first)
                c_on, c_off = _closed_form_thresholds(steps, view)
                rms_px = _rms_own_thresholds(steps, view, c_on, c_off)
                ssr[i] += float(np.nansum(rms_px**2 * view.mask.sum(1)))
    best = int(np.argmin(ssr))
    psf = float(psf_sigmas_px[best])
    # Pass 2: each pixel's thresholds seen through that blur.
    pix, c_on, c_off, rms_px = [], [], [], []
    for y0, y1 in reversed(bands):
        d = band_data(y0, y1)
        if d is None:
            continue
        d = _seen_through(d, seen_charts[best], rig)
        steps = _log_steps(rig, d, overlap=overlap)
        first = sweep_first_events(d, period)
        on0, off0 = _closed_form_thresholds(steps, judged(d, first))
        d, steps = _without_stray_events(
            rig, d, steps, on0, off0, skip=first, overlap=overlap
        )
        on_b, off_b, kept = _sweep_robust_thresholds(steps, judged(d), period)
        rms_b = _robust_spread(steps, dataclasses.replace(d, mask=kept), on_b, off_b)
        pix.append(d.pixel), c_on.append(on_b), c_off.append(off_b)
        rms_px.append(rms_b)
    if not pix:
        raise ValueError("the chart capture has no events on the chart pixels")
    pix, c_on, c_off, rms_px = (np.concatenate(v) for v in (pix, c_on, c_off, rms_px))
    med = np.nanmedian(rms_px)
    mad = np.nanmedian(np.abs(rms_px - med))
    misfit = rms_px > max(2.0 * med, med + 8.0 * 1.4826 * mad, 0.02)
    good_on = np.isfinite(c_on) & ~misfit
    good_off = np.isfinite(c_off) & ~misfit
    on[pix[good_on]] = c_on[good_on]
    off[pix[good_off]] = c_off[good_off]
    maps = on.reshape(h, w), off.reshape(h, w)
    return (*maps, psf) if return_psf else maps


def _row_bands(events: EventStream, budget: int) -> list[tuple[int, int]]:
    """Consecutive bands of sensor rows with at most ~`budget` events each (a row with
    more is a band of its own)."""
    per_row = np.bincount(events.y.astype(np.int64), minlength=events.height)
    bands, y0, total = [], 0, 0
    for y, n in enumerate(per_row):
        if total and total + n > budget:
            bands.append((y0, y))
            y0, total = y, 0
        total += int(n)
    bands.append((y0, events.height))
    return bands


def _without_stray_events(
    rig: Rig, d: ChartData, steps, c_on, c_off, skip=None, overlap=None
):
    """The event lists with each pixel's stray events removed — an event whose residual
    with the pixel's own thresholds `c_on`, `c_off` is beyond max(0.5, 6 robust σ)
    thresholds: a background event inside the lit interval, or a crossing the model
    misses — so the next event refers to the one before it (the simulator's noise
    events do not reset the pixel). One noise event would otherwise bias the pixel's
    thresholds or cost it them (the misfit test); with a gray chart recorded for many
    sweeps many pixels catch one. `steps` are `d`'s model log steps.

    `skip` (`(n, k)` bool, optional): events that are neither judged nor removed
    (each sweep's first: its reference lies across the dark part,
    :func:`sweep_first_events`). `overlap`: as :func:`_log_steps_begin`'s.

    **Returns:** `(d, steps)`, those pixels' lists compacted and their steps
    recomputed."""
    use = d.mask if skip is None else d.mask & ~skip
    r = _own_residuals(steps, d, c_on, c_off)
    r = np.where(use, np.nan_to_num(r, nan=np.inf), 0.0)
    sigma = 1.4826 * float(np.median(np.abs(r[use]))) if use.any() else 0.0
    stray = use & (np.abs(r) > max(STRAY_FLOOR, 6.0 * sigma))
    rows = np.flatnonzero(stray.any(axis=1) & (d.mask.sum(axis=1) > stray.sum(axis=1)))
    if rows.size == 0:
        return d, steps
    sub = d.subset(rows)
    keep = sub.mask & ~stray[rows]
    # Compact each row's remaining events to the front (padding stays at the end).
    order = np.argsort(~keep, axis=1, kind="stable")
    take = lambda a: np.take_along_axis(a, order, axis=1)  # noqa: E731
    sub = dataclasses.replace(
        sub,
        t_us=take(np.where(keep, sub.t_us, 0)),
        polarity=take(np.where(keep, sub.polarity, 0)),
        mask=take(keep),
    )
    full = {k: getattr(d, k).copy() for k in ("t_us", "polarity", "mask")}
    for k in full:
        full[k][rows] = getattr(sub, k)
    steps = steps.copy()
    steps[rows] = _log_steps(rig, sub, overlap=overlap)
    return dataclasses.replace(d, **full), steps


SWEEP_OUTLIER_MADS = 5.0  # a sweep's estimate this many robust σ off is dropped
SWEEP_OUTLIER_FLOOR = 0.01  # ... and at least this fraction of the threshold off


def _sweep_robust_thresholds(steps, d: ChartData, period_us: float):
    """Per-pixel thresholds without the sweeps whose own estimate is an outlier.

    A stray event below the stray-event limit (a background event that lands where
    its step and the next one are both within half a threshold of the model) biases
    every estimate made from its pixel's whole list; on a chart recorded for many
    sweeps most pixels catch one. Each sweep of a pixel gives its own closed-form
    estimate; sweeps beyond `SWEEP_OUTLIER_MADS` robust σ of the pixel's median
    (and beyond `SWEEP_OUTLIER_FLOOR` of it: a noise-free sensor's sweeps agree to
    ~1e-4) are dropped and the rest pooled. With fewer than three sweeps nothing is
    dropped. **Returns:** `(c_on, c_off, mask)` — the events kept.
    """
    sweep = np.floor(np.maximum(d.t_us, 0.0) / period_us).astype(np.int64)
    n_sweeps = int(sweep[d.mask].max()) + 1 if d.mask.any() else 1
    rows = np.broadcast_to(np.arange(d.t_us.shape[0])[:, None], d.t_us.shape)
    keep = d.mask.copy()
    out = []
    for sign in (1, -1):
        sel = d.mask & (d.polarity == sign)
        num = np.zeros((d.t_us.shape[0], n_sweeps))
        den = np.zeros_like(num)
        np.add.at(num, (rows[sel], sweep[sel]), steps[sel] ** 2)
        np.add.at(den, (rows[sel], sweep[sel]), sign * steps[sel])
        with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: no such sweep
            per = np.where(den > 0, num / den, np.nan)
            med = np.nanmedian(per, axis=1, keepdims=True)
            mad = 1.4826 * np.nanmedian(np.abs(per - med), axis=1, keepdims=True)
        limit = np.maximum(SWEEP_OUTLIER_MADS * mad, SWEEP_OUTLIER_FLOOR * med)
        enough = np.isfinite(per).sum(axis=1, keepdims=True) >= 3
        bad = enough & (np.abs(per - med) > limit)
        keep &= ~(sel & bad[rows, sweep])
        good = ~bad & np.isfinite(per)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = (num * good).sum(1) / (den * good).sum(1)
        c[~(c > 0)] = np.nan
        out.append(c)
    return out[0], out[1], keep


def _seen_through(data: ChartData, chart: Scene, rig: Rig) -> ChartData:
    """`data` with each pixel's reflectance taken from `chart` (same geometry)."""
    labels = chart.labels.reshape(-1)[data.pixel]
    used, spectrum = np.unique(labels, return_inverse=True)
    fine = chart.palette_on(rig.grid.fine_edges_nm)[used]
    return dataclasses.replace(data, spectra=fine, spectrum=spectrum.reshape(-1))
