"""The per-pixel quadratic problem: null vectors, anti-drift and spectral priors → (Q, q).

For one pixel with events $(τ_k, σ_k)$ and intensity $I(t) = a(t)\\cdot x + c'$
($c' = c + ε$), the sensor model (paper Eq. 2, reference reset at the end of the
refractory period η) gives for every event

$a(τ_k)\\cdot x + c' = e^{σ_k C_{σ_k}} (a(ρ_k)\\cdot x + c')$,  $ρ_k = τ_{k-1} + η$,

i.e. the augmented null vector $n_k = [a(τ_k) - e^{σ_k C} a(ρ_k);\\ c'(1 - e^{σ_k C})]$
with $n_k \\cdot [x; 1] = 0$. The first event refers to the level at the recording start
($ρ_1 = t_0$, where the band is off the pixel: the known baseline c'), and the chain runs
on across sweeps, so every event is an exact constraint.

**Normalisation.** Taken literally, row $k$ scales with the intensity $I(τ_k)$, so bright
pixels and bright moments dominate and the anti-drift and spectral terms mean different
things at different brightness. Every row is therefore divided by an estimate $\\hat I$
of the intensity it speaks about, making each residual a relative (≈ log) error. The
estimate comes from the events alone: the cumulative polarity $c' \\exp(\\sum σ_i C)$,
restarted at c' each sweep, plus the drift during each refractory period on monotone
flanks (≈ step × η / following gap). The spectral term is divided by the pixel's
brightness estimate $\\hat s^2$, $\\hat s = \\max_k \\hat I_k - c'$.

**Anti-drift** (paper Eq. 17, generalised). The intensity is sampled at `int_points`
times spread over each sweep's *lit interval* (the band overlapping the channel range),
and at each time pulled towards a target built from the two ends of the gap it falls in:
the release $ρ$ after the previous event (or the baseline c' if the band arrived after
it) and the next event (or c' once the band has left, after the sweep's last event).
Targets (`int_target`):

- `"linear"`: the paper's straight line in intensity between the ends;
- `"peak"`: the same plus a bump of `peak_height`·C (relative) where the polarity flips,
  since the level kept moving the old way before it turned (the straight line is biased
  low at a maximum and high at a minimum);
- `"flat"`: interpolate the *apparent reflectance* $(I - c')/F(t)$, $F(t) = \\sum_m
  a_m(t)$ the band's overlap with the channel range, and continue it flat beyond the
  sweep's first/last event — the intensity then falls off correctly as the band leaves
  the channel range, where a straight line in intensity is badly biased;
- `"flat-peak"` (default): `"flat"` with the flip bump.

Each anti-drift row has weight $\\sqrt{α_{int} Δt/τ_0}$ (Δt the sampling step, τ₀ the
time the band takes to move one channel), so the term approximates a time integral and
its weight does not depend on the sampling. Measured on the `tcs` training scene:
ablation in experiments/ablation.py.

**Spectral prior** (paper Eq. 19): $α_{spec} \\sum_{k \\ge M_{start}} (f_k \\cdot x)^2 /
\\hat s^2$ with the DCT-II vectors $f_k$; plus a ridge of `ridge` × mean diagonal, so Q is
positive definite even for a pixel with a single event.

Everything is written for one pixel and vmapped.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._model import BandTable, Rig, lookup
from ._pixels import PixelEvents

__all__ = [
    "ProblemConfig",
    "PixelRows",
    "spectral_prior_matrix",
    "pixel_system",
    "system_from_rows",
]


INT_TARGETS = ("linear", "peak", "flat", "flat-peak")


@dataclasses.dataclass(frozen=True)
class ProblemConfig:
    """Weights and choices of the per-pixel problem (static, hashable).

    - `alpha_int`: weight of the anti-drift term over the whole recording: a
      recording of S sweeps gives each sweep's anti-drift rows alpha_int / S (since
      2026-11-29; before, each sweep had the whole weight, so this prior's pull grew
      with the data and its bias stayed however many sweeps were recorded: README,
      Real sensors, "The anti-drift prior over several sweeps";
      `experiments/anti_drift_sweeps.py`). The paper's 1.0 refers to its
      un-normalised terms; with the normalisation here the events are exact constraints
      and the priors only fill their null space, so the weights are small. Defaults
      chosen on the training scenes `tcs` and a synthetic sharp set (never on the
      evaluation scenes): experiments/tune_weights.py.
    - `alpha_spec`: weight of the spectral prior (tuned likewise).
    - `m_start_frac`: first penalised DCT frequency as a fraction of M (paper: 0.3).
    - `int_points`: anti-drift sample points per sweep (spread over the time the band
      is on the pixel). 24, 36, 48 and 72 gave the same accuracy to 0.01° on the
      ColorChecker, tcs and rainbow scenes. The default was 32 until 2026-11-27; 24
      since: on the training scenes (`tcs`, `sharp`), ideal sensor and `realistic`
      preset, it moved SAM by ≤ 0.002° against 32, while the anti-drift rows are
      about half of each pixel's rows: the ideal fused kernel is 1.10× faster. 20
      lost 0.009° on `tcs` (ideal), 16 lost 0.03° (README, "Anti-drift points";
      `experiments/anti_drift_points.py --speed`).
    - `int_target`: `"linear"` (paper) or `"peak"` (see module docstring).
    - `peak_height`: excursion at a polarity flip, in thresholds (for `"peak"`).
    - `normalise`: divide rows by the intensity estimate (False: the literal paper).
    - `nonneg`: enforce x ≥ 0 (False: unconstrained, for the ablation).
    - `ridge`: relative Tikhonov term keeping Q positive definite.
    - `spec_kind`: `"dct"` (paper) or `"d2"` (local second differences), see
      :func:`spectral_prior_matrix`.
    - `lookup_order`: interpolation of the A(λc) table, 1 (linear, fast) or 3 (cubic,
      continuous derivative — used when the reconstruction is differentiated with
      respect to β, τx or λ0).
    - `noise_floor`: σ₀ (log units), the residual level at which an event row keeps
      weight 1 when a sensor noise model is given (see :func:`pixel_system`); the
      priors' weights above were tuned with rows of about this accuracy.
    - `alpha_dark`: weight of a first-difference prior on channels the rig barely
      lights (weight ∝ peak light / channel light − 1, times the mean share
      $v_k/(q_k + v_k)$ of the event rows' variance that threshold noise would take),
      used with a noise model only, for solves of at most `dark_sweeps` sweeps
      (:func:`dark_strength`).
    - `dark_sweeps`: the dark-channel prior is used for solves of at most this many
      sweeps (1: one sweep, and each sweep of a per-sweep run; since the
      twenty-fifth session, before every length).
      `noise_floor` and `alpha_dark` were chosen on the training scene `tcs` with
      per-crossing threshold noise 0.01 (README "Sensor model"), `dark_sweeps` and the
      share on `tcs` with threshold noise 0.0025–0.02 and timestamp jitter 2–15 µs
      (`experiments/dark_prior.py`), never on the evaluation scenes.
    - `robust_steps`: reweighting passes (Huber weights on the event rows) after the
      first solve when a noise model is given; 0 turns the robust loss off.
    - `lowpass_passes`: at most this many Gauss–Newton passes of the linearised
      photoreceptor model (`x0` of :func:`pixel_system`) after the first,
      delay-shifted solve, when the noise model has a low-pass (with material
      threshold noise or jitter and none, `reconstruct` gives it an instantaneous
      one, `_pipeline.LOG_MODEL_HZ`: log-unit rows), for any number of sweeps
      (until 2026-11-29 only for recordings of ≤ 4: a longer static recording
      kept the delay shift and came out ~3× worse than one of 4 sweeps, README
      "Real sensors"); 0: the first solve alone. The first pass always
      runs; a pixel takes another only while its last pass moved it by more than
      `lowpass_tol` (`evhsi reconstruct --photoreceptor-passes`).
    - `lowpass_tol`: a pixel's Gauss–Newton passes stop once a pass changed its
      spectrum by at most this fraction, ‖x_k − x_{k−1}‖₂ ≤ `lowpass_tol` ‖x_k‖₂
      (0: always `lowpass_passes`). The step
      after a small one is smaller still (the rows carry the model's Jacobian), so
      what it would change is left out. Four pixels share a pass on the fused
      backend (its lanes), so a pixel's second pass costs its group nearly as much
      as four: 0.2 lets ~1 pixel in 100 of the `realistic` preset (10 kHz) take one,
      most pixels of a slow (3 kHz) or quiet photoreceptor (README, Real sensors,
      "The photoreceptor pass").
    - `robust_c`: Huber threshold in standard deviations of a row.
    - `robust_reject`: beyond this many standard deviations a row is dropped (weight
      0) instead of down-weighted: a background event inside the lit interval is not
      a noisy measurement of anything, and Huber's linear influence still lets it
      bend the spectrum.
    - `stray_z`: a pixel whose worst event row is left this many standard
      deviations from its answer is searched for one or two stray (background)
      events inside its lit intervals, and those that explain it are removed (when the
      calibration measured background activity;
      :func:`._pipeline.repair_strays`). 0: never.
    - `max_reflectance`: the reconstructed cube is clipped to [0, this] (a
      non-fluorescent surface reflects at most 1; the margin covers calibration gain
      errors and surfaces brighter than the white reference).
    """

    alpha_int: float = 1e-5
    alpha_spec: float = 3e-6
    m_start_frac: float = 0.3
    int_points: int = 24
    int_target: str = "flat-peak"
    peak_height: float = 0.5
    normalise: bool = True
    nonneg: bool = True
    ridge: float = 1e-9
    spec_kind: str = "d2"
    lookup_order: int = 1
    noise_floor: float = 3e-4
    alpha_dark: float = 1e-6
    dark_sweeps: int = 1
    robust_steps: int = 2
    lowpass_passes: int = 3
    lowpass_tol: float = 0.2
    robust_c: float = 4.0
    robust_reject: float = 12.0
    stray_z: float = 6.0
    max_reflectance: float = 1.5

    def __post_init__(self):
        if self.int_target not in INT_TARGETS:
            raise ValueError(
                f"int_target must be one of {INT_TARGETS}, got {self.int_target!r}"
            )
        if self.int_points < 1:
            raise ValueError("int_points must be >= 1")
        if min(self.alpha_int, self.alpha_spec, self.ridge) < 0:
            raise ValueError("weights must be >= 0")
        if self.lookup_order not in (1, 3):
            raise ValueError(f"lookup_order must be 1 or 3, got {self.lookup_order}")
        if self.spec_kind not in ("dct", "d2"):
            raise ValueError(f"spec_kind must be 'dct' or 'd2', got {self.spec_kind!r}")
        if not 0 < self.m_start_frac <= 1:
            raise ValueError("m_start_frac must be in (0, 1]")
        if self.alpha_dark < 0 or self.dark_sweeps < 0:
            raise ValueError("alpha_dark and dark_sweeps must be >= 0")
        if self.noise_floor <= 0 or self.robust_c <= 0 or self.robust_steps < 0:
            raise ValueError("noise_floor and robust_c must be > 0, robust_steps >= 0")
        if not self.robust_reject > self.robust_c:
            raise ValueError("robust_reject must be > robust_c")
        if not self.max_reflectance > 0:
            raise ValueError("max_reflectance must be > 0")
        if not self.stray_z >= 0:
            raise ValueError("stray_z must be >= 0")
        if self.lowpass_passes < 0 or not self.lowpass_tol >= 0:
            raise ValueError("lowpass_passes and lowpass_tol must be >= 0")


def spectral_prior_matrix(m: int, m_start_frac: float, kind: str = "dct") -> np.ndarray:
    """The spectral prior's Gram matrix, shape `(M, M)`.

    - `"dct"` (paper Eq. 19): $\\sum_{k=\\lceil f M \\rceil}^{M-1} f_k f_k^T$ with DCT-II
      rows $f_k[j] = \\cos(π k (j + ½)/M)$ — a projector on the high frequencies. It is
      non-local: next to a genuine narrow peak it can lower its cost by adding a smooth
      bump far away.
    - `"d2"`: squared second differences $\\sum_j (x_{j-1} - 2x_j + x_{j+1})^2$,
      scaled by $(M/(π \\lceil f M \\rceil))^4$ so that it matches the DCT penalty at
      the cut-off frequency — local (banded), so a peak is only penalised where it is.
    """
    j = np.arange(m) + 0.5
    k0 = int(np.ceil(m_start_frac * m))
    if kind == "dct":
        ks = np.arange(k0, m)
        f = np.cos(np.pi * ks[:, None] * j[None, :] / m)
        return f.T @ f
    if kind == "d2":
        d2 = np.zeros((m - 2, m))
        for r in range(m - 2):
            d2[r, r : r + 3] = (1.0, -2.0, 1.0)
        # A cosine of frequency k has |second difference| ≈ (πk/M)² times its amplitude.
        return d2.T @ d2 * (m / (np.pi * max(k0, 1))) ** 4 * (m / 2)
    raise ValueError(f"unknown spectral prior kind {kind!r}")


def lit_interval_us(rig: Rig, column_offset_us):
    """Local times (within a sweep) at which the band starts and stops touching the
    channel range (band centre at channel start − 2 FWHM and stop + 2 FWHM)."""
    speed = rig.band_speed_nm_per_us
    lo = rig.grid.start_nm - 2.0 * rig.fwhm_nm
    hi = rig.grid.stop_nm + 2.0 * rig.fwhm_nm
    t_arrive = (lo - rig.sweep_start_nm) / speed - column_offset_us
    t_leave = (hi - rig.sweep_start_nm) / speed - column_offset_us
    return t_arrive, t_leave


def pixel_system(
    rig: Rig,
    table: BandTable,
    cfg: ProblemConfig,
    px: PixelEvents,
    sweeps: int,
    *,
    return_gram: bool = False,
    event_scale: Float[ArrayLike, " k"] | None = None,
    noise: Float[ArrayLike, " 3"] | None = None,
    return_rows: bool = False,
    x0: Float[ArrayLike, " m"] | None = None,
):
    """Assemble one pixel's $Q$ (M×M) and $q$ (M) with objective $x^TQx + 2q^Tx$.

    **Arguments:**

    - `rig`, `table`: calibration; `table` is the channel table (`band_table(rig)
      .channels(sub)`).
    - `cfg`: a :class:`ProblemConfig`.
    - `px`: the pixel's events and constants (:class:`PixelEvents`, one pixel).
    - `sweeps`: number of sweeps the recording spans (static).
    - `return_gram`: return the augmented Gram matrix `(M+1, M+1)` (priors added to its
      x block) in place of Q.
    - `event_scale`: optional factor per event row (default 1; the square root of a
      row weight), e.g. the smooth existence weights of marginal events in design
      studies (`evhsi_jax._design`).
    - `noise`: the sensor's noise model `[σ_C, σ_t, d_w]` — per-crossing threshold
      noise (log units), timestamp jitter (µs) and the photoreceptor's delay at a
      white pixel's peak intensity, $d_w = 1/(2π f_c)$ (µs; 0: instantaneous) — or
      `None` for the ideal sensor (every event an exact constraint, as before).
      With a model, (1) each event time is moved back by the low-pass delay at its
      level, $d_w / \\hat I_k$ (a first-order low-pass lags a ramp by its time
      constant), and (2) each event row is weighted by
      $\\sqrt{(σ_0^2 + q_k)/(σ_0^2 + q_k + v_k)}$, $v_k = σ_C^2 + 2σ_t^2 s_k^2$ the
      variance the sensor noise adds to its log residual — a threshold error enters
      as itself, a timing error through the log-intensity's slope
      $s_k ≈ C/(τ_k - ρ_k)$ at both ends of the gap — and $q_k = s_k^2/6$ that of
      the timestamps' rounding (1/12 µs² at each end): an ideal sensor's rows keep
      weight 1. $σ_0$ = `cfg.noise_floor`.
    - `return_rows`: return the weighted rows instead (see :func:`system_from_rows`).
    - `x0`: with a photoreceptor low-pass in `noise`, a previous estimate of the
      spectrum: the event rows are then the photoreceptor model linearised at `x0`
      (:func:`_lowpass_rows`) instead of the delay-shifted exact constraints — one
      Gauss–Newton step of the low-passed sensor model.

    **Returns:** `(Q, q, scale)` — shapes `(M, M)`, `(M,)`, and the brightness
    estimate $\\hat s$ used by the spectral prior.
    """
    dtype = table.values.dtype
    m = table.values.shape[1]
    t_us, polarity, mask = px.t_us, px.polarity, px.mask
    column_offset_us = px.column_offset_us
    threshold_on, threshold_off = px.threshold_on, px.threshold_off
    k = t_us.shape[0]
    t0_phase_us = jnp.asarray(px.t0_phase_us, dtype)
    base = rig.baseline_level
    log_base = jnp.log(base)
    eta = rig.refractory_us
    period = rig.period_us
    sgn = polarity.astype(dtype)
    thr = jnp.where(polarity > 0, threshold_on, threshold_off)
    step = jnp.where(mask, sgn * thr, 0.0)
    ratio = jnp.exp(step)  # e^{σC}

    def a_at(t_rel):
        local = jnp.mod(t_rel + t0_phase_us, period)
        return lookup(
            table, rig.band_centre_nm(local, column_offset_us), order=cfg.lookup_order
        )

    t_arrive, t_leave = lit_interval_us(rig, column_offset_us)
    sweep_of = jnp.floor((t_us + t0_phase_us) / period)
    new_sweep = jnp.concatenate([jnp.array([True]), sweep_of[1:] != sweep_of[:-1]])
    prev_sgn = jnp.concatenate([jnp.zeros((1,), dtype), sgn[:-1]])
    t_raw = t_us
    if noise is not None:
        noise = jnp.asarray(noise, dtype)
        # Photoreceptor lag: each event fired when the low-passed level crossed, about
        # one time constant d_w / I after the level itself did. I from the events.
        lvl0 = log_base + _sweep_cumsum(step, new_sweep, k)
        delay = jnp.minimum(noise[2] * jnp.exp(-lvl0), 5000.0)
        t_us = jnp.where(mask, t_us - delay, t_us)
        t_us = jax.lax.cummax(jnp.where(mask, t_us, -jnp.inf))
        t_us = jnp.where(mask, t_us, 0.0)

    # Reference (release) times: the recording start for the first event, τ_{k-1} + η.
    # t_rel[i] is the release before event i; t_rel[k] the one after the last slot.
    t_rel = jnp.concatenate([jnp.zeros((1,), dtype), t_us + eta])
    a_rel = a_at(t_rel)
    t_ref, a_ref = t_rel[:k], a_rel[:k]
    a_ev = a_at(t_us)
    # Level estimates from the events alone: cumulative polarity, restarted at the
    # baseline at each sweep (the band is off the pixel between sweeps).
    # On a monotone flank the level also moves during each refractory period, by about
    # the step times η / (gap after it): add that drift (release mode only).
    gap = jnp.maximum(t_us - t_ref, 1.0)
    drift = jnp.where(
        (prev_sgn == sgn) & ~new_sweep & (rig.reset_mode == "release"),
        step * jnp.minimum(eta / gap, 3.0),
        0.0,
    )
    level = log_base + _sweep_cumsum(step + drift, new_sweep, k)
    drift_next = jnp.concatenate([drift[1:], jnp.zeros((1,), dtype)])
    i_hat = jnp.exp(level)
    s_hat = jnp.maximum(jnp.max(jnp.where(mask, i_hat, base)) - base, 1e-3 * base)

    norm = cfg.normalise
    w_ev = jnp.where(mask, 1.0 / i_hat if norm else 1.0, 0.0)
    if event_scale is not None:
        w_ev = w_ev * event_scale
    sigma_ev = jnp.full_like(w_ev, cfg.noise_floor)
    if noise is not None:
        slope = jnp.abs(step) / gap
        ideal = cfg.noise_floor**2 + slope**2 / 6.0  # floor + timestamp rounding
        var_c = noise[0] ** 2
        var = var_c + 2.0 * noise[1] ** 2 * slope**2
        w_noise = jnp.sqrt(ideal / (ideal + var))
        w_ev = w_ev * w_noise
        sigma_ev = jnp.sqrt(ideal)
        # How much of the rows' information threshold noise alone would take (0
        # ideal, → 1 noisy): the dark-channel prior's share. Timestamp jitter does not
        # count: it is small where the light changes slowly, which is where the dim
        # channels are read (`dark_strength`).
        n_ev = jnp.maximum(jnp.sum(mask), 1).astype(dtype)
        noisy = jnp.sum(jnp.where(mask, var_c / (ideal + var_c), 0.0)) / n_ev
    ev_rows = (
        jnp.concatenate(
            [a_ev - ratio[:, None] * a_ref, (base * (1.0 - ratio))[:, None]], axis=1
        )
        * w_ev[:, None]
    )
    w_log = None  # the weights of the photoreceptor model's rows (log units)
    if noise is not None:
        w_log = jnp.where(mask, w_noise, 0.0)
        if event_scale is not None:
            w_log = w_log * event_scale
    if x0 is not None and noise is not None:
        lin = _lowpass_rows(
            rig, a_at, jnp.asarray(x0, dtype), noise[2], t_raw, step, t0_phase_us,
            sweeps,
        )  # fmt: skip
        ev_rows = lin * w_log[:, None]

    # Anti-drift rows on a time grid over each sweep's lit interval (when the band is
    # on the pixel): each grid point lies in the gap between two references, and the
    # intensity there is pulled towards the interpolation of the gap's two ends. A gap
    # end is an event (its intensity a·x + c') or, before the band arrives / after the
    # last event of the sweep, the baseline c' (a = 0).
    speed = rig.band_speed_nm_per_us  # nm/µs
    tau0 = rig.grid.width_nm / speed  # µs for the band to move one channel
    g = cfg.int_points
    sw = jnp.arange(sweeps, dtype=dtype)
    t_arrive_s = sw * period - t0_phase_us + t_arrive
    t_leave_s = sw * period - t0_phase_us + t_leave
    spacing = (t_leave - t_arrive) / g
    frac = (jnp.arange(g, dtype=dtype) + 0.5) / g
    t_g = (t_arrive_s[:, None] + frac[None, :] * (t_leave - t_arrive)).reshape(
        -1
    )  # (s*g,)
    sw_g = jnp.repeat(sw, g)
    t_arrive_g = jnp.repeat(t_arrive_s, g)
    t_leave_g = jnp.repeat(t_leave_s, g)
    t_sorted = jnp.where(mask, t_us, jnp.inf)
    nxt = jnp.searchsorted(t_sorted, t_g, side="right", method="compare_all")
    has_next = nxt < jnp.sum(mask).astype(nxt.dtype)
    nxt_c = jnp.minimum(nxt, k - 1)
    prv = nxt - 1
    prv_c = jnp.maximum(prv, 0)
    # End B: the next event if it is in this sweep, else the baseline when the band
    # leaves. End A: the release after the previous event if it happened in this
    # sweep's lit interval, else the baseline when the band arrives.
    b_event = has_next & (sweep_of[nxt_c] == sw_g)
    b_time = jnp.where(b_event, t_us[nxt_c], t_leave_g)
    a_event = (prv >= 0) & (t_rel[prv + 1] >= t_arrive_g) & (sweep_of[prv_c] == sw_g)
    a_time = jnp.where(a_event, t_rel[prv + 1], t_arrive_g)
    a_vec_a = jnp.where(a_event[:, None], a_rel[prv + 1], 0.0)
    a_vec_b = jnp.where(b_event[:, None], a_ev[nxt_c], 0.0)
    i_a = jnp.where(a_event, i_hat[prv_c] * jnp.exp(drift_next[prv_c]), base)
    i_b = jnp.where(b_event, i_hat[nxt_c], base)
    span = jnp.maximum(b_time - a_time, 1.0)
    sg = jnp.clip((t_g - a_time) / span, 0.0, 1.0)
    flip = a_event & b_event & (sgn[prv_c] * sgn[nxt_c] < 0)
    a_g = a_at(t_g)
    if cfg.int_target in ("peak", "flat-peak"):
        bump_h = jnp.where(
            flip, sgn[prv_c] * jnp.expm1(cfg.peak_height * thr[prv_c]), 0.0
        )
    else:
        bump_h = jnp.zeros_like(sg)
    bump = 4.0 * sg * (1.0 - sg) * bump_h
    if cfg.int_target in ("flat", "flat-peak"):
        # Interpolate the apparent reflectance (I - c') / F, F(t) = Σ_m a_m(t) the
        # band's overlap with the channel range; a baseline end continues the other
        # end's value (flat spectrum beyond the last event).
        tiny = 1e-9
        f_g = jnp.sum(a_g, axis=1)
        f_a = jnp.maximum(jnp.sum(a_vec_a, axis=1), tiny)
        f_b = jnp.maximum(jnp.sum(a_vec_b, axis=1), tiny)
        wa_f = jnp.where(a_event, jnp.where(b_event, 1.0 - sg, 1.0), 0.0) + bump
        wb_f = jnp.where(b_event, jnp.where(a_event, sg, 1.0), 0.0)
        int_x = (
            a_g
            - (wa_f * f_g / f_a)[:, None] * a_vec_a
            - (wb_f * f_g / f_b)[:, None] * a_vec_b
        )
        int_c = jnp.zeros_like(sg)
        i_tgt = base + f_g * (wa_f * (i_a - base) / f_a + wb_f * (i_b - base) / f_b)
        i_tgt = jnp.maximum(i_tgt, base)
    else:
        wa = 1.0 - sg + bump
        int_x = a_g - wa[:, None] * a_vec_a - sg[:, None] * a_vec_b
        int_c = -base * bump
        i_tgt = jnp.maximum(wa * i_a + sg * i_b, 1e-3 * base)
    # alpha_int is the prior's weight over the whole recording: each of its sweeps
    # repeats the same assumption about the same spectrum, so each gets 1/sweeps.
    w_int = jnp.sqrt(cfg.alpha_int / sweeps * spacing / tau0) * jnp.ones_like(sg)
    if norm:
        w_int = w_int / i_tgt
    int_rows = jnp.concatenate([int_x, int_c[:, None]], axis=1) * w_int[:, None]

    spec_w = cfg.alpha_spec / (s_hat**2 if norm else 1.0)
    strength = dark_strength(sweeps, cfg)
    if noise is not None and strength > 0:
        # Channels the rig barely lights carry little data; with noisy rows their
        # values would follow the noise. Tie each to its neighbour with a weight that
        # grows as the channel's light falls (0 for a fully lit channel) and with the
        # share of the rows' variance threshold noise takes (0 for an ideal sensor).
        light = jnp.max(table.values, axis=0)
        dim = jnp.minimum(jnp.max(light) / jnp.maximum(light, 1e-12) - 1.0, 1e4)
        # Its rows (x_{c+1} − x_c)·wd_c add a tridiagonal term to the Gram matrix
        # (`dark_gram`): kept as the weights wd², not as M−1 dense rows.
        dark = strength * noisy * 0.5 * (dim[1:] + dim[:-1]) / s_hat**2
    else:
        dark = None
    if return_rows:
        return PixelRows(ev_rows, int_rows, spec_w, s_hat, sigma_ev, w_log, dark)
    rows = jnp.concatenate([ev_rows, int_rows], axis=0)
    gram = dark_gram(rows.T @ rows, dark)
    return _system(cfg, m, gram, spec_w, s_hat, return_gram)


def dark_strength(sweeps: int, cfg: ProblemConfig) -> float:
    """The dark-channel prior's weight for a solve of `sweeps` sweeps:
    `cfg.alpha_dark` for up to `cfg.dark_sweeps` sweeps (default 1), 0 for more.

    The prior ties each dim channel to its neighbour so that one sweep's noisy rows
    do not carry it away; it also pulls real spectral detail flat. Each pixel's share
    of it is the share of its rows' variance that threshold noise alone would take
    (:func:`pixel_system`): timestamp jitter does not count, as it is small where the
    light changes slowly, which is where the dim channels are read. Both since the
    twenty-fifth session (before, every noisy solve of any length got it, jitter
    counted): on the training scene `tcs` (true rig and thresholds, 32×48) a
    recording of two sweeps with threshold noise 0.01 reached 3.2° SAM without it
    against 4.7° with it, and one sweep with 2–5 µs of jitter 1.9–2.7° against
    3.4–4.5° (README, Real sensors, "The dark-channel prior's strength";
    `experiments/dark_prior.py`)."""
    return cfg.alpha_dark if sweeps <= cfg.dark_sweeps else 0.0


def dark_gram(gram, dark):
    """`gram` `(M+1, M+1)` plus the dark-channel prior's Gram term for weights `dark`
    `(M−1,)` (None: none): Σ_c dark_c (e_{c+1} − e_c)(e_{c+1} − e_c)ᵀ, tridiagonal —
    what its M−1 rows would add, without forming them."""
    if dark is None:
        return gram
    c = jnp.arange(dark.shape[0])
    gram = gram.at[c, c].add(dark).at[c + 1, c + 1].add(dark)
    return gram.at[c, c + 1].add(-dark).at[c + 1, c].add(-dark)


def dark_rows(dark):
    """The dark-channel prior's rows `(…, M−1, M+1)` for weights `dark` `(…, M−1)`:
    (x_{c+1} − x_c)·√dark_c (the zero last column acts on the constant) — for a
    consumer that takes rows only (the CUDA kernel)."""
    n = dark.shape[-1]
    d1 = jnp.eye(n + 1, dtype=dark.dtype)[1:] - jnp.eye(n + 1, dtype=dark.dtype)[:-1]
    rows = d1 * jnp.sqrt(dark)[..., :, None]
    return jnp.pad(rows, [(0, 0)] * (rows.ndim - 1) + [(0, 1)])


class PixelRows(NamedTuple):
    """One pixel's weighted least-squares rows (for reweighting without re-assembly).

    `events` `(k, M+1)` and `drift` `(g, M+1)` act on $[x; 1]$; `spec_weight` is the
    spectral prior's weight; `sigma` `(k,)` each event row's ideal-sensor deviation (log
    units) before its noise weight: a weighted row's residual divided by it is the
    residual in standard deviations. `log_weight` `(k,)`, with a noise model: each
    event's weight in the photoreceptor model's rows (:func:`_lowpass_rows`, whose
    rows are in log units: the noise weight alone), None without one. `dark`
    `(M−1,)`: the dark-channel prior's weights (:func:`dark_gram`; its rows are not
    in `drift`), None without it."""

    events: Array
    drift: Array
    spec_weight: Array
    s_hat: Array
    sigma: Array
    log_weight: Array | None = None
    dark: Array | None = None


def system_from_rows(cfg: ProblemConfig, rows: PixelRows, row_weight=None):
    """$(Q, q)$ of :func:`pixel_system` from its rows, the event rows scaled by
    `row_weight` `(k,)` (e.g. robust-loss weights; default 1)."""
    ev = rows.events if row_weight is None else rows.events * row_weight[:, None]
    gram = dark_gram(ev.T @ ev + rows.drift.T @ rows.drift, rows.dark)
    m = gram.shape[0] - 1
    return _system(cfg, m, gram, rows.spec_weight, rows.s_hat, False)


#: How :func:`_lowpass_rows` runs the filter's recursion: "auto" — a sequential scan
#: on a CPU, an associative scan elsewhere (a GPU runs its log-depth levels in
#: parallel); "sequential" or "associative" to choose. On 2 CPU cores (2026-12-07,
#: JAX backend, 48×72 ColorChecker, `realistic` preset, float32,
#: `experiments/bench_reconstruct.py --backends jax --lowpass-scan ...`): on one XLA
#: device the first call took 77 s instead of 94 s and each later one 13.5 s instead
#: of 23.1 s; on two, 61.9 s against 60.7 s and 10.7 s against 12.9 s; the same
#: cube to the printed digits (SAM 4.878°, PSNR 28.80 dB).
LOWPASS_SCAN = "auto"


def _sequential_scan() -> bool:
    if LOWPASS_SCAN == "auto":
        return jax.default_backend() == "cpu"
    return LOWPASS_SCAN == "sequential"


def _lowpass_rows(rig, a_at, x0, d_w, t_us, step, t0_phase_us, sweeps):
    r"""Event rows of the low-passed sensor, linearised at `x0`, in log units.

    The photoreceptor output obeys $y_j = α_j y_{j-1} + (1-α_j) L_j$ on the rig's time
    grid, $L = \log(a\cdot x + c')$, $α_j = \exp(-Δt\,I_j/d_w)$ (the simulator's
    model, :func:`evhsi_jax.forward.photoreceptor_lowpass`), and event k says
    $y(τ_k) - y(ρ_k) = σ_k C$. Linearised at $x_0$ (a Gauss–Newton step): $y$ at
    $x_0$ is the filtered $L_0$, and its Jacobian $J_j = ∂y_j/∂x$ obeys
    $J_j = α_j J_{j-1} + w_j a_j$ with
    $w_j = (1-α_j)/I'_j - (y_{j-1} - L_j)\,α_j Δt/d_w$ ($I' = I + ε$): the first
    term is $L$'s own slope, the second the decay's (a brighter pixel's filter is
    faster), which a fixed decay leaves out — without it each pass converged only
    linearly (a 3 kHz photoreceptor needed ~6 passes instead of 2,
    `experiments/photoreceptor_pass.py`). Row k is
    $[ΔJ;\ ΔF_{L_0} - ΔJ\cdot x_0 - σ_k C]$ with $Δ$ the difference between $τ_k$
    and $ρ_k$ (linear interpolation between grid points, as the simulator's
    crossings).
    """
    dtype = x0.dtype
    n = rig.samples_per_sweep
    period = rig.period_us
    dt = period / n
    g_n = sweeps * n + 1
    tg = jnp.arange(g_n, dtype=dtype) * dt - t0_phase_us
    ag = a_at(tg)
    inten = jnp.maximum(ag @ x0 + rig.baseline_rel, 0.0)
    lev = inten + rig.log_eps
    log_lev = jnp.log(lev)
    dtw = dt / jnp.maximum(d_w, 1e-6)
    alpha = jnp.exp(-dtw * inten).at[0].set(0.0)

    def filtered(inputs):  # the filter's recursion over the grid, per column
        if _sequential_scan():

            def step(y, a_in):
                y = a_in[0] * y + a_in[1]
                return y, y

            return jax.lax.scan(step, jnp.zeros_like(inputs[0]), (alpha, inputs))[1]

        def combine(left, right):
            return left[0] * right[0], right[0][:, None] * left[1] + right[1]

        return jax.lax.associative_scan(combine, (alpha, inputs), axis=0)[1]

    # y at x0 first: the decay's part of the Jacobian needs y at the point before.
    y = filtered(((1.0 - alpha) * log_lev)[:, None])
    y_prev = jnp.concatenate([jnp.zeros((1, 1), dtype), y[:-1]])[:, 0]
    w = (1.0 - alpha) / lev - (y_prev - log_lev) * alpha * dtw
    filt = jnp.concatenate([y, filtered(w[:, None] * ag)], axis=1)

    def at(t):
        # A carried reference before the recording (t0_phase_us < 0) is read one
        # period later: the band's schedule repeats, so a filter started a sweep
        # before it sees what this one, started at the recording, sees a sweep later
        # (`_fused_jit._lowpass_queries`; clamped to the baseline before 2026-11-29).
        pos = (t + t0_phase_us) / dt
        pos = jnp.where(pos < 0.0, pos + n, pos)
        pos = jnp.clip(pos, 0.0, g_n - 1.0)
        i = jnp.clip(jnp.floor(pos), 0, g_n - 2)
        f = (pos - i)[:, None]
        i = i.astype(jnp.int32)
        return filt[i] * (1.0 - f) + filt[i + 1] * f

    t_ref = jnp.concatenate([jnp.zeros((1,), dtype), t_us[:-1] + rig.refractory_us])
    d = at(t_us) - at(t_ref)
    row_x = d[:, 1:]
    row_c = d[:, 0] - row_x @ x0 - step
    return jnp.concatenate([row_x, row_c[:, None]], axis=1)


def _sweep_cumsum(step, new_sweep, k):
    """Cumulative sum of the log steps, restarted at 0 at the start of each sweep
    (the level before each sweep's first event is the baseline)."""
    seg = jnp.cumsum(new_sweep) - 1
    cum = jnp.cumsum(step)
    base = jax.ops.segment_min(
        jnp.where(new_sweep, cum - step, jnp.inf), seg, num_segments=k
    )
    return cum - base[seg]


def _system(cfg, m, gram, spec_w, s_hat, return_gram):
    dtype = gram.dtype
    spec_np = spectral_prior_matrix(m, cfg.m_start_frac, cfg.spec_kind)
    # Traces without materialising a sum of two (M, M) matrices per pixel.
    trace = jnp.sum(jnp.diagonal(gram)[:m]) + spec_w * float(np.trace(spec_np))
    ridge = cfg.ridge * (trace / m + 1e-30)
    prior = spec_w * jnp.asarray(spec_np, dtype) + ridge * jnp.eye(m, dtype=dtype)
    if return_gram:
        return gram.at[:m, :m].add(prior), gram[:m, m], s_hat
    return gram[:m, :m] + prior, gram[:m, m], s_hat
