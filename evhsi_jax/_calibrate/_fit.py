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

from .._model import (
    BandTable,
    Calibration,
    EventStream,
    Rig,
    Scene,
    band_overlap,
    lookup,
)
from .._reconstruct import lit_interval_us, noise_model, screen_events
from ._chart import (
    ChartData,
    _closed_form_thresholds,
    _device,
    _log_steps,
    _with_column_offsets,
    chart_data,
    chart_residuals,
    spectral_traces,
    threshold_maps_from_chart,
)

__all__ = [
    "CalibrationResult",
    "calibrate",
    "spectral_correction",
    "apply_spectral_correction",
    "save_calibration",
]

TAU_SCALE_US = 100.0  # τx parameter unit in the solver
CURV_SCALE_NM = 1.0  # sweep-curvature parameter unit in the solver
SMOOTH_WEIGHT = 0.02  # residual weight of one µs of τx second difference


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
    return jax.jvp(
        lambda q: _fit_residuals(q, (False, None, fit))[0], (p0,), (tangent,)
    )[1]


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
        extra["sweep_curvature_nm"] = (
            base.sweep_curvature_nm + CURV_SCALE_NM * params["curv"]
        )
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
                "hot_pixels": int(
                    0 if self.hot_pixels is None else self.hot_pixels.sum()
                ),
                "threshold_noise": float(e.threshold_noise),
                "timestamp_jitter_us": float(e.timestamp_jitter_us),
                "noise_rate_hz": float(self.rig.noise_rate_hz),
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
    t_ref = np.concatenate(
        [np.zeros_like(t[:, :1]), t[:, :-1] + float(rig.refractory_us)], axis=1
    )  # noqa: E501
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
    from .._model import exact_events_scan

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


def _screened_chart_data(
    events, chart, rig, t_start_us, rows_per_label, from_data, fit_baseline
):
    """The chart's per-pixel event lists with background activity and hot pixels
    screened out (when starting from the data), checked for enough events and
    levels: `(data, screened events, hot-pixel map)`."""
    data = chart_data(
        events, chart, rig, t_start_us=t_start_us, rows_per_label=rows_per_label
    )
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
    return data, events, hot


def _jacobi_scale(p0: dict, fit: _FitData, dev, shape, w: int) -> dict:
    """Each parameter's Jacobian column norm at `p0` (floored): the change of variables
    of :func:`_fit_chart_float64`."""
    dtype = p0["tau"].dtype
    res_col = jnp.broadcast_to(dev[3][:, None], shape).reshape(-1)

    def jcol(tangent):
        return _fit_jvp(p0, tangent, fit)

    zero_t = jax.tree.map(jnp.zeros_like, p0)
    scale = {}
    for k in ("log_on", "log_off", "log_beta", "log_c") + (
        ("curv",) if "curv" in p0 else ()
    ):
        scale[k] = jnp.linalg.norm(jcol({**zero_t, k: jnp.ones((), dtype)}))
    scale["resp"] = (
        jnp.stack(
            [
                jnp.linalg.norm(
                    jcol({**zero_t, "resp": jnp.eye(p0["resp"].size, dtype=dtype)[j]})
                )
                for j in range(p0["resp"].size)
            ]
        )
        if p0["resp"].size
        else jnp.zeros((0,), dtype)
    )
    d_tau = jcol({**zero_t, "tau": jnp.ones((w,), dtype)})
    scale["tau"] = jnp.sqrt(jax.ops.segment_sum(d_tau**2, res_col, num_segments=w))
    scale = {
        k: jnp.maximum(v, 1e-6 * jnp.max(v) + 1e-30) if v.size else v
        for k, v in scale.items()
    }
    return scale


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
    captured = events
    data, events, hot = _screened_chart_data(
        events, chart, rig, t_start_us, rows_per_label, from_data, fit_baseline
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
    scale = _jacobi_scale(p0, fit, dev, data.t_us.shape, w)

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
    fitted = fitted.replace_host(
        threshold_noise=noise["threshold_noise"],
        timestamp_jitter_us=noise["timestamp_jitter_us"],
        noise_rate_hz=bg_rate,
        **({} if psf is None else {"psf_sigma_px": psf}),
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
    f = f * np.asarray(rig.channel_gain)  # (ones when there is no correction yet)
    return rig.replace_host(channel_gain=[float(v) for v in f])
