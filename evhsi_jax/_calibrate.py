"""Calibration: fit the rig to captures of a chart of known reflectance.

**Residuals.** For every event of a chart pixel (known reflectance, used on the fine
grid), the sensor model (release mode, paper Eq. 2) says
$d_k = \\log(I(τ_k) + ε) - \\log(I(ρ_k) + ε) = σ_k C_{σ_k}$, $ρ_k = τ_{k-1} + η$ (the
recording start for the first event). The residual is $r_k = d_k / C - σ_k$, in units of
the threshold (see :func:`chart_residuals` for why not log units): the forward model's
own equations at the *observed* event times — smooth in every parameter, finite
everywhere ($I + ε \\ge c + ε > 0$), and with no reconstruction inside. They are
fitted jointly with optimistix's Levenberg–Marquardt for the ON/OFF thresholds, the
sweep coefficient β, the constant light c, a smooth correction of D(λ) and one time
offset τx per column (with a second-difference smoothness prior
across columns); the normal equations are solved matrix-free (lineax NormalCG), so a
1280-column sensor (≈1300 unknowns) needs no dense Jacobian.

**What gray patches can and cannot separate.**

- ON/OFF thresholds and c: separable — patches of different known reflectance see the
  same light at different levels, and the number and spacing of events depend on
  $\\log(R F(t)/c + 1)/C$ differently for different R.
- β and τx: separable from each other because the band's entry into and exit from the
  channel range (the sharp rise at 400 nm and fall at 760 nm) are two time anchors per
  column, 360 nm / (βω) apart.
- λ0 (`sweep_start_nm`) is *not* separable from τx (λc depends on λ0 + βωτx only); it is
  kept fixed and τx absorbs it.
- β against an unknown camera response D(λ): a flat gray patch only sees D·E blurred by
  the band, so a mis-scaled β is equivalent to a stretched D except at the range edges.
  With the edges as anchors β is fixed here; on a rig without band-limiting filters a
  target of known spectral structure (a narrow-band filter or laser line at a known
  wavelength, or a white reference with a spectrometer reading) is needed.
- D(λ): a flat gray patch sees D·E through the *shape* of its intensity trace (the
  band blurs it), so a wrong D biases everything else; a smooth correction of D (a few
  Legendre terms of log D, `response_degree`) is therefore fitted jointly. Its overall
  scale is not identifiable (the peak normalisation removes it), and structure finer
  than the band is not seen: per-channel factors come from a white reference of known
  spectrum (:func:`spectral_correction`, paper supplement 6.1).
- Per-pixel thresholds: with the global parameters fixed, each pixel's residuals are
  linear in its own C_on, C_off: closed-form means of the observed log steps
  (:func:`threshold_maps_from_chart`). Needs ≥ 1 ON and ≥ 1 OFF event per pixel; pixels
  without get the global value.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ._calibration import Calibration
from ._events import EventStream
from ._illumination import BandTable, band_overlap, band_table, lookup
from ._reconstruct import group_pixels, lit_interval_us, noise_model, screen_events
from ._rig import Rig
from ._scenes import Scene
from ._sensor import photoreceptor_lowpass

__all__ = [
    "ChartData",
    "chart_data",
    "chart_residuals",
    "CalibrationResult",
    "calibrate",
    "threshold_maps_from_chart",
    "spectral_correction",
    "apply_spectral_correction",
    "save_calibration",
]

TAU_SCALE_US = 100.0  # τx parameter unit in the solver
CURV_SCALE_NM = 1.0  # sweep-curvature parameter unit in the solver
SMOOTH_WEIGHT = 0.02  # residual weight of one µs of τx second difference


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
) -> ChartData:
    """Select chart pixels and pad their events into one array.

    **Arguments:**

    - `events`: the capture; `chart`: the chart scene (same size as the sensor).
    - `rig`: for the channel grid.
    - `t_start_us`: sweep phase 0 (default: first trigger, else 0).
    - `rows_per_label`: keep at most this many rows of each chart patch per column
      (evenly spread) to bound the work; `None` keeps all pixels.
    - `max_events`: at most this many events per pixel (the earliest).
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
    pix = events.y.astype(np.int64) * events.width + events.x
    sel = keep.reshape(-1)[pix]
    sub = events.take(np.nonzero(sel)[0])
    batches, counts, _ = group_pixels(
        sub,
        t_start_us=t_start_us,
        chunk_pixels=events.width * events.height,
        min_chunk=1,
        max_events=max_events,
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


def spectral_traces(rig: Rig, spectra, overlap: BandTable | None = None) -> BandTable:
    """Intensity above c of each chart spectrum vs band centre: `(n_λ, S)` table.

    The chart's few spectra are known, so their traces over λc are tabulated once (the
    fine band table times each fine reflectance); a residual then needs a 1-D
    interpolation instead of a 360-wide dot product. Differentiable in the rig's FWHM,
    D and E through the band table. `overlap`: the rig's :func:`band_overlap`, when the
    caller keeps the band fixed and has it already (the joint fit: it is most of the
    cost otherwise); then D and E are still differentiable, the FWHM is not.
    """
    if overlap is None:
        table = band_table(rig)
        return BandTable(
            table.values @ jnp.asarray(spectra, table.values.dtype).T,
            table.lo_nm,
            table.step_nm,
        )
    weight = rig.camera_response * rig.lamp
    gain = 1.0 / jnp.max(overlap.values @ weight)
    weighted = weight[:, None] * jnp.asarray(spectra, overlap.values.dtype).T
    return BandTable(gain * (overlap.values @ weighted), overlap.lo_nm, overlap.step_nm)


def chart_log_steps(rig: Rig, data, traces=None):
    """Model log steps of every chart event, shape `(n, k)` (0 in padding).

    `data` is a :class:`ChartData`, or the tuple `(t, polarity, mask, column,
    spectrum)` of JAX arrays (then `traces` is required). Differentiable in the rig.
    """
    if isinstance(data, ChartData):
        traces = traces if traces is not None else spectral_traces(rig, data.spectra)
        data = _device(data, rig.fwhm_nm.dtype)
    elif traces is None:
        raise ValueError("pass the spectral traces with device arrays")
    t, _, m, col, s_idx = data
    offsets = rig.column_offsets(_width(rig, col))[col][:, None]
    base = rig.baseline_level
    # References: the recording start for the first event, then τ_{k-1} + η.
    t_ref = jnp.concatenate(
        [jnp.zeros_like(t[:, :1]), t[:, :-1] + rig.refractory_us], axis=1
    )

    def level(tt):
        # Only each pixel's own chart spectrum is interpolated: the linearisation
        # that Levenberg–Marquardt keeps then holds (n, k) arrays, not (n, k, S).
        a = lookup(
            traces, rig.band_centre_nm(tt, offsets), order=3, column=s_idx[:, None]
        )
        return jnp.log(jnp.maximum(a, 0.0) + base)

    hz = rig.effects.photoreceptor_hz
    if hz > 0:  # a known photoreceptor low-pass: the events see the filtered level
        ftab = _lowpassed_traces(rig, traces, hz)

        def level(tt):
            return lookup(
                ftab, rig.band_centre_nm(tt, offsets), order=3, column=s_idx[:, None]
            )

    return jnp.where(m, level(t) - level(t_ref), 0.0)


def _lowpassed_traces(rig: Rig, traces: BandTable, cutoff_hz: float) -> BandTable:
    """The chart spectra's log-intensity traces through the photoreceptor low-pass
    (:func:`evhsi_jax.forward.photoreceptor_lowpass`), tabulated over λc like the
    traces: time and λc are proportional along the sweep (one table step is
    `step / (βω)` µs), so the filter runs along the table. Exact for the chart (its
    spectra are known); differentiable in the rig."""
    speed = rig.band_speed_nm_per_us
    inten = jnp.maximum(traces.values, 0.0) + rig.baseline_rel
    filt = photoreceptor_lowpass(
        jnp.log(inten + rig.log_eps),
        traces.step_nm / speed,
        cutoff_hz,
        rig.log_eps,
    )
    return BandTable(filt, traces.lo_nm, traces.step_nm)


def chart_residuals(rig: Rig, data, traces=None, *, per_pixel: bool = False):
    """Event residuals in threshold units, shape `(n, k)` (0 in padding).

    $r_k = d_k / C - σ_k$ with $d_k$ the model log step (:func:`chart_log_steps`): 0
    when the model explains event k exactly. Dividing by C (rather than residuals
    $d_k - σ_kC$ in log units) matters: in log units a rig with huge constant light
    and tiny thresholds would explain any events with tiny residuals; in threshold
    units the observed, geometric spacing of event levels rules it out.

    With `per_pixel`, each pixel's own ON and OFF thresholds are profiled out:
    $1/C_p = \\sum σ_k d_k / \\sum d_k^2$ over the pixel's events of one polarity
    (the least-squares value), so threshold mismatch cannot bias the other parameters.
    """
    d = chart_log_steps(rig, data, traces)
    pol = data.polarity if isinstance(data, ChartData) else data[1]
    mask = data.mask if isinstance(data, ChartData) else data[2]
    pol = jnp.asarray(pol).astype(d.dtype)
    pos = jnp.asarray(mask) & (pol > 0)
    neg = jnp.asarray(mask) & (pol < 0)
    if per_pixel:

        def inv_c(sel, sign):
            num = jnp.sum(jnp.where(sel, sign * d, 0.0), 1, keepdims=True)
            den = jnp.sum(jnp.where(sel, d * d, 0.0), 1, keepdims=True)
            ok = den > 0
            return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)

        u = jnp.where(pos, inv_c(pos, 1.0), inv_c(neg, -1.0))
    else:
        u = jnp.where(pol > 0, 1.0 / rig.threshold_on, 1.0 / rig.threshold_off)
    return jnp.where(pos | neg, d * u - pol, 0.0)


def _with_column_offsets(rig: Rig, width: int) -> Rig:
    """`rig` with its column offsets explicit (one per column)."""
    if rig.column_offsets_us is not None:
        return rig
    return rig.with_leaves(column_offsets_us=rig.column_offsets(width))


def _width(rig, col):
    if rig.column_offsets_us is None:
        raise ValueError("calibration needs explicit column offsets (one per column)")
    return rig.column_offsets_us.shape[0]


def _device(d: ChartData, dtype):
    return (
        jnp.asarray(d.t_us, dtype),
        jnp.asarray(d.polarity, jnp.int32),
        jnp.asarray(d.mask),
        jnp.asarray(d.column),
        jnp.asarray(d.spectrum),
    )


# --- the joint fit ---------------------------------------------------------------------
def _normal_cg(rtol, atol):
    """CG on the normal equations (matrix-free): `lx.Normal(lx.CG)` in newer lineax,
    `lx.NormalCG` before it."""
    if hasattr(lx, "Normal"):
        return lx.Normal(lx.CG(rtol=rtol, atol=atol))
    return lx.NormalCG(rtol=rtol, atol=atol)


def _response_basis(rig: Rig, degree: int) -> np.ndarray:
    """Legendre polynomials P1..P_degree over the channel range, on the fine grid
    (`(degree, F)`): the smooth log-correction of D(λ) a gray chart can identify (P0 is
    the overall scale, which the peak normalisation removes)."""
    g = rig.grid
    u = 2.0 * (g.fine_centres_nm - g.start_nm) / (g.stop_nm - g.start_nm) - 1.0
    return np.stack(
        [np.polynomial.legendre.Legendre.basis(j)(u) for j in range(1, degree + 1)]
    )


class _FitData(eqx.Module):
    """What the chart-fit residuals read besides the parameters (all arguments, no
    closures: see `_fit_chart_float64`)."""

    rig: Rig
    basis: Any
    dev: Any
    spectra: Any
    fixed_traces: Any
    overlap: Any  # the band's overlap table: the band is not fitted, so computed once
    overlap_lo_nm: float = eqx.field(static=True)
    overlap_step_nm: float = eqx.field(static=True)
    fit_baseline: bool = eqx.field(static=True)


def _fit_residuals(params, args):
    """Chart residuals (per event) and the τx smoothness prior of the joint fit."""
    profile, keep, fit = args
    r = _apply(params, fit.rig, fit.basis)
    if not fit.fit_baseline:
        r = r.with_leaves(baseline_rel=fit.rig.baseline_rel)
    traces = (
        BandTable(fit.fixed_traces, fit.overlap_lo_nm, fit.overlap_step_nm)
        if fit.fixed_traces is not None
        else spectral_traces(
            r,
            fit.spectra,
            BandTable(fit.overlap, fit.overlap_lo_nm, fit.overlap_step_nm),
        )
    )
    res = chart_residuals(r, fit.dev, traces, per_pixel=profile)
    if keep is not None:
        res = res * keep[:, None]
    # The prior acts on the absolute offsets (the starting guess may be rough).
    tau = fit.rig.column_offsets_us + TAU_SCALE_US * params["tau"]
    smooth = SMOOTH_WEIGHT * (tau[2:] - 2 * tau[1:-1] + tau[:-2])
    return res.reshape(-1), smooth


def _fit_residuals_scaled(u, args):
    """`_fit_residuals` in the solver's scaled variables u = θ·s."""
    scale, inner = args
    return _fit_residuals(jax.tree.map(lambda a, b: a / b, u, scale), inner)


_fit_residuals_jit = eqx.filter_jit(_fit_residuals)


@eqx.filter_jit
def _fit_jvp(p0, tangent, fit):
    return jax.jvp(lambda q: _fit_residuals(q, (False, None, fit))[0], (p0,), (tangent,))[
        1
    ]


@eqx.filter_jit
def _fit_sum_sq(params, args):
    return jnp.sum(_fit_residuals(params, args)[0] ** 2)


def _apply(params, base: Rig, basis=None) -> Rig:
    """Solver parameters (normalised) → rig."""
    if basis is not None and basis.shape[0]:
        resp = base.camera_response * jnp.exp(
            params["resp"] @ jnp.asarray(basis, base.fwhm_nm.dtype)
        )
        base = base.with_leaves(camera_response=resp / jnp.max(resp))
    extra = {}
    if "curv" in params:
        extra["sweep_curvature_nm"] = base.sweep_curvature_nm + CURV_SCALE_NM * params[
            "curv"
        ]
    return base.with_leaves(
        threshold_on=base.threshold_on * jnp.exp(params["log_on"]),
        threshold_off=base.threshold_off * jnp.exp(params["log_off"]),
        beta_nm_per_rad=base.beta_nm_per_rad * jnp.exp(params["log_beta"]),
        baseline_rel=base.baseline_rel * jnp.exp(params["log_c"]),
        column_offsets_us=base.column_offsets_us + TAU_SCALE_US * params["tau"],
        **extra,
    )


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """A fitted rig and how the fit went."""

    rig: Rig
    threshold_on_map: np.ndarray | None
    threshold_off_map: np.ndarray | None
    hot_pixels: np.ndarray | None
    converged: bool  # Levenberg–Marquardt met its tolerances (else: max_steps)
    outlier_pixels: int  # chart pixels dropped for unexplained events
    rms_residual: float  # threshold units (1 = one threshold), over all fitted events
    rms_residual_initial: float
    steps: int
    events_used: int
    pixels_used: int
    seconds: float
    psf_sigma_px: float | None = None  # the chart's blur chosen for the maps

    @property
    def calibration(self) -> Calibration:
        """The result as a :class:`Calibration` (what `reconstruct` takes)."""
        e = self.rig.effects
        return Calibration(
            self.rig,
            self.threshold_on_map,
            self.threshold_off_map,
            self.hot_pixels,
            {
                "rms_residual_thresholds": self.rms_residual,
                "rms_residual_initial": self.rms_residual_initial,
                "converged": self.converged,
                "steps": self.steps,
                "events_used": self.events_used,
                "pixels_used": self.pixels_used,
                "outlier_pixels": self.outlier_pixels,
                "hot_pixels": int(0 if self.hot_pixels is None else self.hot_pixels.sum()),
                "threshold_noise": e.threshold_noise,
                "timestamp_jitter_us": e.timestamp_jitter_us,
                "noise_rate_hz": self.rig.noise_rate_hz,
                "psf_sigma_px": self.psf_sigma_px,
                "seconds": self.seconds,
                "not_measured": "photoreceptor_hz (kept from the initial rig)",
            },
        )


SCREEN_MARGIN_US = 500.0  # lit-interval margin when screening a chart capture
MAX_RMS_RESIDUAL = 0.5  # threshold units: above, the capture is not the chart


def _sweeps_of(events, rig, t_start_us) -> int:
    span = float(events.t_us[-1] - t_start_us) if len(events) else 0.0
    return max(1, int(np.ceil((span + 1.0) / float(rig.period_us))))


def _outlier_pixels(r: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Pixels with a residual beyond max(0.5, 8 robust σ) threshold units."""
    vals = np.abs(r[mask])
    if vals.size == 0:
        return np.zeros(r.shape[0], bool)
    sigma = 1.4826 * np.median(vals)
    limit = max(0.5, 8.0 * sigma)
    return np.any((np.abs(r) > limit) & mask, axis=1)


def measure_noise(rig: Rig, data: ChartData, residuals: np.ndarray) -> dict:
    """Per-crossing threshold noise and timestamp jitter from the fitted residuals.

    A residual $r_k$ (threshold units, each pixel's own thresholds profiled out) times
    C is the event's log-step error, whose variance is $σ_C^2 + 2σ_t^2 s_k^2$ plus
    the timestamps' rounding $2 s_k^2/12$ (the model of
    :func:`evhsi_jax.reconstruction.pixel_system`), $s_k$ the log-intensity's slope
    at the event — on a chart known from the model. The two are separable because
    the slope differs from event to event: least squares of $(r_k C)^2$ on
    $[1, 2 s_k^2]$, after dropping the top 1 % (outliers), each clipped at 0. The
    photoreceptor's low-pass is not identified here (its mean delay is absorbed by
    the column offsets).

    **Returns:** `{"threshold_noise": σ_C, "timestamp_jitter_us": σ_t}`.
    """
    c = 0.5 * (float(rig.threshold_on) + float(rig.threshold_off))
    steps = _log_steps(rig, data)
    t = data.t_us
    t_ref = np.concatenate([np.zeros_like(t[:, :1]), t[:, :-1] + float(rig.refractory_us)], axis=1)  # noqa: E501
    slope = np.abs(steps) / np.maximum(t - t_ref, 1.0)
    m = data.mask & np.isfinite(residuals)
    m[:, 0] = False  # the first event refers to the recording start
    e2 = (residuals * c)[m] ** 2
    s2 = 2.0 * slope[m] ** 2
    if e2.size < 10:
        return {"threshold_noise": 0.0, "timestamp_jitter_us": 0.0}
    keep = e2 <= np.quantile(e2, 0.99)
    a = np.stack([np.ones(keep.sum()), s2[keep]], axis=1)
    coef, *_ = np.linalg.lstsq(a, e2[keep] - s2[keep] / 12.0, rcond=None)
    return {
        "threshold_noise": float(np.sqrt(max(coef[0], 0.0))),
        "timestamp_jitter_us": float(np.sqrt(max(coef[1], 0.0))),
    }


def _background_rate(events, hot, rig, t_start_us) -> float:
    """Background-activity rate per pixel (Hz): events outside the lit intervals of
    pixels that are not hot, over the dark time they had."""
    sweeps = _sweeps_of(events, rig, t_start_us)
    kept, _, _ = screen_events(events, rig, t_start_us, noise_model(rig), sweeps, hot)
    h, w = events.height, events.width
    n_out = len(events) - len(kept) - int(np.isin(
        events.y.astype(np.int64) * w + events.x, np.flatnonzero(hot)
    ).sum())  # fmt: skip
    offs = np.asarray(rig.column_offsets(w), np.float64)
    t_arrive, t_leave = (np.asarray(v, np.float64) for v in lit_interval_us(rig, offs))
    dark = float(np.mean(float(rig.period_us) - (t_leave - t_arrive) - 400.0)) * sweeps
    n_pix = max(h * w - int(hot.sum()), 1)
    return max(n_out, 0) / (n_pix * max(dark, 1.0) * 1e-6)


def initial_guess(data: ChartData, rig: Rig) -> Rig:
    """Column offsets and β from the data: first and last event time per column.

    For each chart reflectance the exact pixel model, run along the band-centre
    wavelength λc with the initial rig, gives the λc at which the first ON and the last
    OFF event of a sweep fire, λ_on and λ_off — independent of β and τx. The observed
    times t_on, t_off (first sweep) then give
    $β = (λ_{off} - λ_{on}) / (ω\\,\\mathrm{median}(t_{off} - t_{on}))$ and per column
    $τ_x = (λ_{on} - λ_0)/(βω) - t_{on}$ (medians over the column's pixels).
    """
    from ._sensor import exact_events_scan

    traces = spectral_traces(rig, data.spectra)
    step_nm = 0.25
    n_tab = traces.values.shape[0]
    lam = np.arange(traces.lo_nm, traces.lo_nm + traces.step_nm * (n_tab - 1), step_nm)
    a = np.asarray(lookup(traces, jnp.asarray(lam, traces.values.dtype)), np.float64)
    base = float(rig.baseline_level)
    uniq = np.arange(data.spectra.shape[0])
    inv = data.spectrum
    log_i = np.log(np.maximum(a, 0.0) + base)  # (λ, S): λ plays the role of time
    omega = float(rig.omega_rad_per_us)
    eta_nm = float(rig.refractory_us) * float(rig.beta_nm_per_rad) * omega
    dtype = rig.fwhm_nm.dtype
    (fired, tc, _), _ = exact_events_scan(
        jnp.asarray(log_i, dtype),
        jnp.asarray(lam, dtype),
        jnp.full(uniq.shape[0], rig.threshold_on, dtype),
        jnp.full(uniq.shape[0], rig.threshold_off, dtype),
        jnp.asarray(eta_nm, dtype),
    )
    fired, tc = np.asarray(fired), np.asarray(tc, np.float64)
    any_ev = fired.any(axis=0)
    first_i = np.argmax(fired, axis=0)
    last_i = fired.shape[0] - 1 - np.argmax(fired[::-1], axis=0)
    lam_on_u = tc[first_i, np.arange(uniq.shape[0])]
    lam_off_u = tc[last_i, np.arange(uniq.shape[0])]
    lam_on, lam_off = lam_on_u[inv.ravel()], lam_off_u[inv.ravel()]
    period = float(rig.period_us)
    in_first = data.mask & (data.t_us < period)
    n_first = in_first.sum(axis=1)
    ok = any_ev[inv.ravel()] & (n_first >= 2)
    if ok.sum() < 3:
        raise ValueError(
            "too few chart pixels have events in the first sweep: is the capture lit, "
            "and do the chart and sensor size match?"
        )
    idx = np.arange(data.t_us.shape[0])
    t_on = data.t_us[:, 0]
    t_off = data.t_us[idx, np.maximum(n_first - 1, 0)]
    beta = np.median((lam_off - lam_on)[ok]) / (omega * np.median((t_off - t_on)[ok]))
    if not np.isfinite(beta) or beta <= 0:
        raise ValueError("could not estimate the sweep coefficient from the capture")
    tau_pix = (lam_on - float(rig.sweep_start_nm)) / (beta * omega) - t_on
    w = data.width
    tau = np.full(w, np.nan)
    for x in range(w):
        s = ok & (data.column == x)
        if s.any():
            tau[x] = np.median(tau_pix[s])
    good = np.isfinite(tau)
    tau = np.interp(np.arange(w), np.nonzero(good)[0], tau[good])
    return rig.with_leaves(
        beta_nm_per_rad=jnp.asarray(beta, dtype),
        column_offsets_us=jnp.asarray(tau, dtype),
    )


def calibrate(events: EventStream, chart: Scene, init: Rig, **kw) -> CalibrationResult:
    """Fit thresholds, β, c and per-column τx to a chart capture (then per-pixel maps).

    Always computed in float64 — event times of long captures and residuals of a few
    1e-4 in log units over 10⁵–10⁶ events are below float32 resolution, and the
    Levenberg–Marquardt stopping tests need it — and returned in `init`'s dtype. See
    :func:`_fit_chart_float64` for the arguments.
    """
    dtype = init.fwhm_nm.dtype
    with jax.enable_x64(True):
        res = _fit_chart_float64(events, chart, init.astype(jnp.float64), **kw)
        rig = res.rig.astype(dtype)
    return dataclasses.replace(res, rig=rig)


def _fit_chart_float64(
    events: EventStream,
    chart: Scene,
    init: Rig,
    *,
    t_start_us: int | None = None,
    rows_per_label: int | None = 4,
    per_pixel: bool = True,
    max_steps: int = 60,
    fit_baseline: bool = True,
    from_data: bool = True,
    response_degree: int = 4,
    fit_curvature: bool = True,
    verbose: bool = False,
) -> CalibrationResult:
    """Fit thresholds, β, c and per-column τx to a chart capture (then per-pixel maps).

    **Arguments:**

    - `events`: capture of `chart` (one or more sweeps); `init`: the initial rig.
    - `t_start_us`: sweep phase 0 (default: first trigger, else 0).
    - `rows_per_label`: rows of each patch used for the global fit (per column).
    - `per_pixel`: also estimate per-pixel threshold maps (all pixels).
    - `max_steps`: Levenberg–Marquardt steps.
    - `fit_baseline`: fit c (else kept).
    - `from_data`: start β and τx from :func:`initial_guess` instead of `init`'s.
    - `response_degree`: fit a smooth correction of the camera response,
      $D(λ) \\exp(\\sum_{j=1}^{n} w_j P_j)$ (Legendre polynomials over the channel range):
      a gray chart sees D·E through the shape of its intensity traces, so a wrong D would
      otherwise bias everything else. 0 keeps D.
    - `fit_curvature`: fit the sweep's parabolic non-linearity `sweep_curvature_nm`
      (the band's entry and exit anchor the ends; the lamp's and camera's spectral
      structure inside the range places the middle).

    **Returns:** a :class:`CalibrationResult`.
    """
    import time

    t0 = time.perf_counter()
    w = events.width
    rig = _with_column_offsets(init, w)
    if rig.column_offsets_us.shape[0] != w:
        raise ValueError(
            f"initial rig has {rig.column_offsets_us.shape[0]} column offsets, the "
            f"capture is {w} columns wide"
        )
    if t_start_us is None:
        t_start_us = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    data = chart_data(
        events, chart, rig, t_start_us=t_start_us, rows_per_label=rows_per_label
    )
    captured = events
    if from_data:
        # Background activity and hot pixels are not in the model: find them with a
        # first guess of the sweep's timing, drop their events, then start again.
        rig0 = initial_guess(data, rig)
        events, hot, _ = screen_events(
            events, rig0, t_start_us, None, _sweeps_of(events, rig0, t_start_us),
            margin_us=SCREEN_MARGIN_US,
        )  # fmt: skip
        data = chart_data(
            events, chart, rig, t_start_us=t_start_us, rows_per_label=rows_per_label
        )
    else:
        hot = np.zeros((events.height, events.width), bool)
    n_on = int((data.mask & (data.polarity > 0)).sum())
    n_off = int((data.mask & (data.polarity < 0)).sum())
    if n_on < 10 or n_off < 10:
        raise ValueError(
            f"too few events to calibrate ({n_on} ON, {n_off} OFF on chart pixels); "
            "need a lit capture of the chart with at least a few events per patch"
        )
    levels = np.unique(np.round(data.spectra.mean(axis=1), 4))
    if fit_baseline and levels.size < 2:
        raise ValueError(
            "the chart has a single reflectance level: thresholds and the constant "
            "light cannot be separated (use a chart with several gray levels, or "
            "fit_baseline=False)"
        )
    if from_data:
        rig = initial_guess(data, rig)
    dtype = rig.fwhm_nm.dtype
    dev = _device(data, dtype)
    basis = _response_basis(rig, response_degree)
    fixed_traces = (  # the table's values (a BandTable is not a pytree leaf holder)
        None if response_degree else spectral_traces(rig, data.spectra).values
    )
    p0 = {
        "log_on": jnp.zeros((), dtype),
        "log_off": jnp.zeros((), dtype),
        "log_beta": jnp.zeros((), dtype),
        "log_c": jnp.zeros((), dtype),
        **({"curv": jnp.zeros((), dtype)} if fit_curvature else {}),
        "tau": jnp.zeros((w,), dtype),
        "resp": jnp.zeros((response_degree,), dtype),
    }

    keep = jnp.ones(data.t_us.shape[0], dtype)  # pixels in the fit (outliers: 0)
    # Everything the residuals read travels as arguments (not closed over), so each
    # compiled function depends on shapes only: one compilation per shape in a
    # process, and the persistent cache serves the next process.
    overlap = band_overlap(rig)
    fit = _FitData(rig, basis, dev, jnp.asarray(data.spectra, dtype), fixed_traces,
                   overlap.values, overlap.lo_nm, overlap.step_nm,
                   fit_baseline)  # fmt: skip

    def residuals(params, args):
        profile, keep = args if isinstance(args, tuple) else (args, None)
        return _fit_residuals_jit(params, (profile, keep, fit))

    # Jacobi scaling by change of variables (u = θ·s, s = column norms of the Jacobian at
    # the start): the Gauss–Newton matrix then has a unit diagonal and is "identity plus
    # the rank-4 coupling of the global parameters", so the matrix-free CG inside each
    # Levenberg–Marquardt step converges in a few iterations. Each residual depends on
    # one τx only, so one JVP with all-ones τ tangents gives every column's norm.
    res_col = jnp.broadcast_to(dev[3][:, None], data.t_us.shape).reshape(-1)

    def jcol(tangent):
        return _fit_jvp(p0, tangent, fit)

    zero_t = jax.tree.map(jnp.zeros_like, p0)
    scale = {}
    for k in ("log_on", "log_off", "log_beta", "log_c") + (
        ("curv",) if fit_curvature else ()
    ):
        scale[k] = jnp.linalg.norm(jcol({**zero_t, k: jnp.ones((), dtype)}))
    scale["resp"] = (
        jnp.stack(
            [
                jnp.linalg.norm(
                    jcol({**zero_t, "resp": jnp.eye(response_degree, dtype=dtype)[j]})
                )
                for j in range(response_degree)
            ]
        )
        if response_degree
        else jnp.zeros((0,), dtype)
    )
    d_tau = jcol({**zero_t, "tau": jnp.ones((w,), dtype)})
    scale["tau"] = jnp.sqrt(jax.ops.segment_sum(d_tau**2, res_col, num_segments=w))
    scale = {
        k: jnp.maximum(v, 1e-6 * jnp.max(v) + 1e-30) if v.size else v
        for k, v in scale.items()
    }

    def theta_of(u):
        return jax.tree.map(lambda a, b: a / b, u, scale)

    def rms_of(params, profile):
        n = int((data.mask & (np.asarray(keep) > 0)[:, None]).sum())
        return float(jnp.sqrt(_fit_sum_sq(params, (profile, keep, fit)) / max(n, 1)))

    r0 = rms_of(p0, False)
    solver = optx.LevenbergMarquardt(
        rtol=1e-7,
        atol=1e-9,
        # An inexact Gauss–Newton step is enough inside Levenberg–Marquardt.
        linear_solver=_normal_cg(rtol=1e-4, atol=1e-9),
        verbose=bool(verbose),
    )
    # Stage 1: one threshold pair for all pixels. Stage 2 (per_pixel): the same fit with
    # every pixel's thresholds profiled out, so per-pixel mismatch cannot bias β, c, τx;
    # the thresholds then follow in closed form and the rig's global pair is their mean.
    u, steps = jax.tree.map(lambda a, b: a * b, p0, scale), 0
    converged = True
    outlier_pixels = 0
    for profile in (False, True) if per_pixel else (False,):
        sol = optx.least_squares(
            _fit_residuals_scaled,
            solver,
            u,
            args=(scale, (profile, keep, fit)),
            max_steps=max_steps,
            throw=False,
        )
        steps += int(sol.stats["num_steps"])
        converged = sol.result == optx.RESULTS.successful
        u = sol.value
        params = theta_of(u)
        if not all(bool(jnp.all(jnp.isfinite(v))) for v in jax.tree.leaves(params)):
            raise ValueError("the calibration diverged (non-finite parameters)")
        if verbose:
            print(
                f"calibrate (profiled={profile}): {sol.result}, rms "
                f"{rms_of(params, profile):.5f}"
            )
        if not profile:
            # Robustness: a pixel with an event the model cannot explain (a noise
            # event inside the lit interval, a missed crossing) is dropped whole —
            # one bad event also corrupts its neighbour's reference.
            r = np.asarray(residuals(params, per_pixel)[0]).reshape(data.t_us.shape)
            bad_px = _outlier_pixels(r, data.mask)
            outlier_pixels = int(bad_px.sum())
            if 0 < outlier_pixels < 0.5 * bad_px.size:
                keep = jnp.asarray(~bad_px, dtype)
    rms = rms_of(params, per_pixel)
    res_final = np.asarray(residuals(params, (per_pixel, keep))[0])
    res_final = res_final.reshape(data.t_us.shape)
    data = dataclasses.replace(data, mask=data.mask & (np.asarray(keep) > 0)[:, None])
    fitted = _apply(params, rig, basis)
    if not fit_baseline:
        fitted = fitted.with_leaves(baseline_rel=rig.baseline_rel)
    on_map = off_map = psf = None
    if per_pixel:
        on_map, off_map, psf = threshold_maps_from_chart(
            events, chart, fitted, t_start_us=t_start_us, return_psf=True
        )
        # The population thresholds: mean over the chart pixels that had such events.
        c_on, c_off = _closed_form_thresholds(_log_steps(fitted, data), data)
        fitted = fitted.with_leaves(
            threshold_on=jnp.asarray(np.nanmean(c_on), dtype),
            threshold_off=jnp.asarray(np.nanmean(c_off), dtype),
        )
    noise = measure_noise(fitted, data, res_final)
    bg_rate = _background_rate(captured, hot, fitted, t_start_us)
    if rms > MAX_RMS_RESIDUAL:
        raise ValueError(
            f"the calibration does not fit its data: RMS residual {rms:.2f} thresholds "
            f"after {steps} steps (a gray-chart capture of this rig fits to < "
            f"{MAX_RMS_RESIDUAL}); is the capture a gray chart of the given size, "
            "lit by the sweep?"
        )
    fitted = fitted.replace_static(
        effects=dataclasses.replace(
            fitted.effects,
            threshold_noise=noise["threshold_noise"],
            timestamp_jitter_us=noise["timestamp_jitter_us"],
        ),
        noise_rate_hz=bg_rate,
    )
    return CalibrationResult(
        rig=fitted,
        threshold_on_map=on_map,
        threshold_off_map=off_map,
        hot_pixels=hot,
        converged=bool(converged),
        outlier_pixels=outlier_pixels,
        rms_residual=rms,
        rms_residual_initial=r0,
        steps=steps,
        events_used=data.events,
        pixels_used=int(data.mask.any(axis=1).sum()),
        seconds=time.perf_counter() - t0,
        psf_sigma_px=psf,
    )


_log_steps_jit = eqx.filter_jit(chart_log_steps)


def _log_steps(rig: Rig, data: ChartData, block: int = 4096):
    """Model log steps of every chart event in blocks of pixels, `(n, k)` (host).

    Every block is padded to `block` pixels (masked), so one compilation serves all.
    """
    traces = spectral_traces(rig, data.spectra)
    dtype = rig.fwhm_nm.dtype
    n = data.t_us.shape[0]
    block = min(block, n)
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
        steps = np.asarray(
            _log_steps_jit(rig, _device(part, dtype), traces), np.float64
        )
        out.append(steps[: block - pad])
    return np.concatenate(out)


PSF_GRID_PX = (0.0, 0.25, 0.4, 0.5, 0.6, 0.75, 1.0, 1.5)  # blur σ searched, pixels


def _rms_own_thresholds(steps, data: ChartData, c_on, c_off) -> np.ndarray:
    """Per-pixel RMS residual (threshold units) with the pixel's own thresholds."""
    c_px = np.where(data.polarity > 0, c_on[:, None], c_off[:, None])
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(data.mask, steps / c_px - data.polarity, np.nan)
        return np.sqrt(np.nanmean(r**2, axis=1))


def _closed_form_thresholds(steps: np.ndarray, data: ChartData):
    """Per-pixel C_on, C_off from model log steps: the least-squares values of the
    threshold-unit residuals, $C = \\sum d_k^2 / \\sum σ_k d_k$ (NaN where a pixel has
    no event of that polarity)."""
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
):
    """Per-pixel ON/OFF thresholds with the global parameters fixed (closed form).

    Each event's model log step $d_k = \\log I(τ_k) - \\log I(ρ_k)$ is computed from the
    known reflectance; a pixel's $C_{on}$ is the mean of $d_k$ over its ON events and
    $C_{off}$ the mean of $-d_k$ over its OFF events (the least-squares solution of its
    residuals).

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

    **Returns:** `(threshold_on, threshold_off)` maps, each `(H, W)`; with
    `return_psf` also the chosen σ (pixels).
    """
    h, w = events.height, events.width
    rig = _with_column_offsets(rig, w)
    on = np.full(h * w, float(rig.threshold_on))
    off = np.full(h * w, float(rig.threshold_off))
    data = chart_data(events, chart, rig, t_start_us=t_start_us, rows_per_label=None)
    best = None
    seen = [_seen_through(data, chart.blurred(float(v)), rig) for v in psf_sigmas_px]
    # One padded spectra count (a power of two) for every blur: one compilation.
    rows = 1 << max(max(d.spectra.shape[0] for d in seen) - 1, 1).bit_length()
    for sigma, d in zip(psf_sigmas_px, seen):
        d = dataclasses.replace(
            d, spectra=np.pad(d.spectra, ((0, rows - d.spectra.shape[0]), (0, 0)))
        )
        steps = _log_steps(rig, d)
        c_on, c_off = _closed_form_thresholds(steps, d)
        rms_px = _rms_own_thresholds(steps, d, c_on, c_off)
        ssr = float(np.nansum(rms_px**2 * d.mask.sum(1)))
        if best is None or ssr < best[0]:
            best = (ssr, float(sigma), d, steps, c_on, c_off, rms_px)
    _, psf, d, steps, c_on, c_off, rms_px = best
    c_on, c_off, rms_px = _refit_without_stray_events(rig, d, steps, c_on, c_off, rms_px)
    med = np.nanmedian(rms_px)
    mad = np.nanmedian(np.abs(rms_px - med))
    misfit = rms_px > max(2.0 * med, med + 8.0 * 1.4826 * mad, 0.02)
    good_on = np.isfinite(c_on) & ~misfit
    good_off = np.isfinite(c_off) & ~misfit
    on[data.pixel[good_on]] = c_on[good_on]
    off[data.pixel[good_off]] = c_off[good_off]
    maps = on.reshape(h, w), off.reshape(h, w)
    return (*maps, psf) if return_psf else maps


def _refit_without_stray_events(rig: Rig, d: ChartData, steps, c_on, c_off, rms_px):
    """Closed-form thresholds again for pixels with a stray event — one whose residual
    with the pixel's own thresholds is beyond max(0.5, 6 robust σ) thresholds: a
    background event inside the lit interval, or a crossing the model misses — with
    that event removed from the pixel's list (so the next event refers to the one
    before it). One noise event would otherwise cost the whole pixel its own
    thresholds (it would fail the misfit test); with a gray chart recorded for many
    sweeps most pixels catch one. `steps` are `d`'s model log steps."""
    c_px = np.where(d.polarity > 0, c_on[:, None], c_off[:, None])
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(d.mask, steps / c_px - d.polarity, 0.0)
    r = np.nan_to_num(r, nan=np.inf)
    sigma = 1.4826 * float(np.median(np.abs(r[d.mask]))) if d.mask.any() else 0.0
    stray = d.mask & (np.abs(r) > max(0.5, 6.0 * sigma))
    rows = np.flatnonzero(stray.any(axis=1) & (d.mask.sum(axis=1) > stray.sum(axis=1)))
    if rows.size == 0:
        return c_on, c_off, rms_px
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
    steps2 = _log_steps(rig, sub)
    on2, off2 = _closed_form_thresholds(steps2, sub)
    rms2 = _rms_own_thresholds(steps2, sub, on2, off2)
    c_on, c_off, rms_px = c_on.copy(), c_off.copy(), rms_px.copy()
    c_on[rows], c_off[rows], rms_px[rows] = on2, off2, rms2
    return c_on, c_off, rms_px


def _seen_through(data: ChartData, chart: Scene, rig: Rig) -> ChartData:
    """`data` with each pixel's reflectance taken from `chart` (same geometry)."""
    labels = chart.labels.reshape(-1)[data.pixel]
    used, spectrum = np.unique(labels, return_inverse=True)
    fine = chart.palette_on(rig.grid.fine_edges_nm)[used]
    return dataclasses.replace(data, spectra=fine, spectrum=spectrum.reshape(-1))


def save_calibration(path, result: CalibrationResult, *, comment: str = "") -> dict:
    """Write a calibration file pair (:meth:`Calibration.save`): the rig JSON with every
    key and the measured sensor noise, and a sibling `<stem>_thresholds.npz` with the
    per-pixel maps that the JSON names. Both atomic.

    **Returns:** the JSON object written.
    """
    cal = result.calibration
    report = dict(cal.report)
    report["comment"] = (
        (comment + ": " if comment else "")
        + f"rms residual {result.rms_residual:.2e} (start "
        f"{result.rms_residual_initial:.2e}) thresholds over {result.events_used} events "
        f"of {result.pixels_used} pixels, {result.steps} LM steps, {result.seconds:.0f} s"
    )
    return dataclasses.replace(cal, report=report).save(path)


def spectral_correction(
    cube: np.ndarray, reference: np.ndarray, *, floor: float = 0.05
):
    """Per-channel response factors from a white reference (paper supplement 6.1).

    Reconstruct a capture of a reference of known spectrum with the calibrated rig;
    whatever makes the reconstruction differ from the reference in the same way at every
    pixel — a camera response D(λ) different from the rig's, or any other systematic
    per-channel error — appears as the ratio reconstruction / truth. The factors are the
    median over pixels of that ratio per channel. Store them as the rig's
    `channel_gain` (:func:`apply_spectral_correction`); reconstructions are then divided
    by them. (An error of D within a channel scales that channel's A(t) column, hence its
    reconstructed value, by the same factor, so the correction acts on the output and
    leaves the forward model — and the calibrated c and thresholds — untouched.)

    **Arguments:**

    - `cube`: reconstruction of the reference capture, `(H, W, M)`.
    - `reference`: the reference's true reflectance on the channel grid, `(M,)` or
      `(H, W, M)`.
    - `floor`: channels where the reference is below this reflectance get factor 1.

    **Returns:** factors, shape `(M,)`.
    """
    cube = np.asarray(cube, np.float64)
    ref = np.broadcast_to(np.asarray(reference, np.float64), cube.shape)
    ok = ref > floor
    ratio = np.where(ok, cube / np.where(ok, ref, 1.0), np.nan)
    with np.errstate(invalid="ignore"):
        f = np.nanmedian(ratio.reshape(-1, cube.shape[-1]), axis=0)
    return np.where(np.isfinite(f) & (f > 0), f, 1.0)


def apply_spectral_correction(rig: Rig, factors) -> Rig:
    """A rig whose reconstructions are divided by per-channel `factors` (M,), combined
    with any correction it already has (the factors multiply)."""
    f = np.asarray(factors, np.float64)
    if f.shape != (rig.channels,) or np.any(~np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"need {rig.channels} positive finite correction factors")
    if rig.channel_gain is not None:
        f = f * np.asarray(rig.channel_gain)
    return rig.replace_static(channel_gain=tuple(float(v) for v in f))
