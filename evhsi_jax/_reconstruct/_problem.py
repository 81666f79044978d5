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

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._illumination import BandTable, lookup
from .._rig import Rig

__all__ = ["ProblemConfig", "spectral_prior_matrix", "pixel_system"]


INT_TARGETS = ("linear", "peak", "flat", "flat-peak")


@dataclasses.dataclass(frozen=True)
class ProblemConfig:
    """Weights and choices of the per-pixel problem (static, hashable).

    - `alpha_int`: weight of the anti-drift term. The paper's 1.0 refers to its
      un-normalised terms; with the normalisation here the events are exact constraints
      and the priors only fill their null space, so the weights are small. Defaults
      chosen on the training scenes `tcs` and a synthetic sharp set (never on the
      evaluation scenes): experiments/tune_weights.py.
    - `alpha_spec`: weight of the spectral prior (tuned likewise).
    - `m_start_frac`: first penalised DCT frequency as a fraction of M (paper: 0.3).
    - `int_points`: anti-drift sample points per sweep (spread over the time the band
      is on the pixel). 24, 36, 48 and 72 gave the same accuracy to 0.01° on the
      ColorChecker, tcs and rainbow scenes; 32 keeps the Gram matrix (the main cost)
      small.
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
    """

    alpha_int: float = 1e-5
    alpha_spec: float = 3e-6
    m_start_frac: float = 0.3
    int_points: int = 32
    int_target: str = "flat-peak"
    peak_height: float = 0.5
    normalise: bool = True
    nonneg: bool = True
    ridge: float = 1e-9
    spec_kind: str = "d2"
    lookup_order: int = 1

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


def _peak_b(peak_height: float) -> float:
    # h(s) = -s + b s(1-s) peaks at (b-1)^2 / (4b) = p  ⇒  b = 1+2p + sqrt((1+2p)^2 - 1).
    u = 1.0 + 2.0 * peak_height
    return u + np.sqrt(u * u - 1.0)


def lit_interval_us(rig: Rig, column_offset_us):
    """Local times (within a sweep) at which the band starts and stops touching the
    channel range (band centre at channel start − 2 FWHM and stop + 2 FWHM)."""
    speed = rig.beta_nm_per_rad * rig.omega_rad_per_us
    lo = rig.grid.start_nm - 2.0 * rig.fwhm_nm
    hi = rig.grid.stop_nm + 2.0 * rig.fwhm_nm
    u_arr = (lo - rig.sweep_start_nm) / speed - column_offset_us
    u_lv = (hi - rig.sweep_start_nm) / speed - column_offset_us
    return u_arr, u_lv


def pixel_system(
    rig: Rig,
    table: BandTable,
    cfg: ProblemConfig,
    t_us: Float[Array, " k"],
    polarity: Int[Array, " k"],
    mask: Bool[Array, " k"],
    column_offset_us: Float[ArrayLike, ""],
    threshold_on: Float[ArrayLike, ""],
    threshold_off: Float[ArrayLike, ""],
    t0_phase_us: Float[ArrayLike, ""],
    sweeps: int,
    *,
    return_gram: bool = False,
    event_scale: Float[ArrayLike, " k"] | None = None,
):
    """Assemble one pixel's $Q$ (M×M) and $q$ (M) with objective $x^TQx + 2q^Tx$.

    **Arguments:**

    - `rig`, `table`: calibration; `table` is the channel table (`band_table(rig)
      .channels(sub)`).
    - `cfg`: a :class:`ProblemConfig`.
    - `t_us`: event times relative to the recording start, µs, shape `(k,)` (padded at
      the end; padding is ignored).
    - `polarity`: ±1 per event (0 in padding); `mask`: real events.
    - `column_offset_us`: τx of the pixel's column.
    - `threshold_on`, `threshold_off`: the pixel's thresholds (log units).
    - `t0_phase_us`: recording start modulo the sweep period.
    - `sweeps`: number of sweeps the recording spans (static).
    - `return_gram`: return the augmented Gram matrix `(M+1, M+1)` (priors added to its
      x block) in place of Q.
    - `event_scale`: optional factor per event row (default 1; the square root of a
      row weight), e.g. the smooth existence weights of marginal events in design
      studies (`evhsi_jax._design`).

    **Returns:** `(Q, q, scale)` — shapes `(M, M)`, `(M,)`, and the brightness
    estimate $\\hat s$ used by the spectral prior.
    """
    dtype = table.values.dtype
    m = table.values.shape[1]
    k = t_us.shape[0]
    t0_phase_us = jnp.asarray(t0_phase_us, dtype)
    c1 = rig.baseline_rel + rig.log_eps
    log_c1 = jnp.log(c1)
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

    u_arr, u_lv = lit_interval_us(rig, column_offset_us)
    sweep_of = jnp.floor((t_us + t0_phase_us) / period)

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
    new_sweep = jnp.concatenate([jnp.array([True]), sweep_of[1:] != sweep_of[:-1]])
    prev_sgn = jnp.concatenate([jnp.zeros((1,), dtype), sgn[:-1]])
    gap = jnp.maximum(t_us - t_ref, 1.0)
    drift = jnp.where(
        (prev_sgn == sgn) & ~new_sweep & (rig.reset_mode == "release"),
        step * jnp.minimum(eta / gap, 3.0),
        0.0,
    )
    seg = jnp.cumsum(new_sweep) - 1
    cum = jnp.cumsum(step + drift)
    base = jax.ops.segment_min(
        jnp.where(new_sweep, cum - step, jnp.inf), seg, num_segments=k
    )
    level = log_c1 + cum - base[seg]
    drift_next = jnp.concatenate([drift[1:], jnp.zeros((1,), dtype)])
    i_hat = jnp.exp(level)
    s_hat = jnp.maximum(jnp.max(jnp.where(mask, i_hat, c1)) - c1, 1e-3 * c1)

    norm = cfg.normalise
    w_ev = jnp.where(mask, 1.0 / i_hat if norm else 1.0, 0.0)
    if event_scale is not None:
        w_ev = w_ev * event_scale
    ev_rows = (
        jnp.concatenate(
            [a_ev - ratio[:, None] * a_ref, (c1 * (1.0 - ratio))[:, None]], axis=1
        )
        * w_ev[:, None]
    )

    # Anti-drift rows on a time grid over each sweep's lit interval (when the band is
    # on the pixel): each grid point lies in the gap between two references, and the
    # intensity there is pulled towards the interpolation of the gap's two ends. A gap
    # end is an event (its intensity a·x + c') or, before the band arrives / after the
    # last event of the sweep, the baseline c' (a = 0).
    speed = rig.beta_nm_per_rad * rig.omega_rad_per_us  # nm/µs
    tau0 = rig.grid.width_nm / speed  # µs for the band to move one channel
    g = cfg.int_points
    sw = jnp.arange(sweeps, dtype=dtype)
    t_arr_s = sw * period - t0_phase_us + u_arr
    t_lv_s = sw * period - t0_phase_us + u_lv
    spacing = (u_lv - u_arr) / g
    frac = (jnp.arange(g, dtype=dtype) + 0.5) / g
    t_g = (t_arr_s[:, None] + frac[None, :] * (u_lv - u_arr)).reshape(-1)  # (s*g,)
    sw_g = jnp.repeat(sw, g)
    t_arr_g = jnp.repeat(t_arr_s, g)
    t_lv_g = jnp.repeat(t_lv_s, g)
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
    b_time = jnp.where(b_event, t_us[nxt_c], t_lv_g)
    a_event = (prv >= 0) & (t_rel[prv + 1] >= t_arr_g) & (sweep_of[prv_c] == sw_g)
    a_time = jnp.where(a_event, t_rel[prv + 1], t_arr_g)
    a_vec_a = jnp.where(a_event[:, None], a_rel[prv + 1], 0.0)
    a_vec_b = jnp.where(b_event[:, None], a_ev[nxt_c], 0.0)
    i_a = jnp.where(a_event, i_hat[prv_c] * jnp.exp(drift_next[prv_c]), c1)
    i_b = jnp.where(b_event, i_hat[nxt_c], c1)
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
        i_tgt = c1 + f_g * (wa_f * (i_a - c1) / f_a + wb_f * (i_b - c1) / f_b)
        i_tgt = jnp.maximum(i_tgt, c1)
    else:
        wa = 1.0 - sg + bump
        int_x = a_g - wa[:, None] * a_vec_a - sg[:, None] * a_vec_b
        int_c = -c1 * bump
        i_tgt = jnp.maximum(wa * i_a + sg * i_b, 1e-3 * c1)
    w_int = jnp.sqrt(cfg.alpha_int * spacing / tau0) * jnp.ones_like(sg)
    if norm:
        w_int = w_int / i_tgt
    int_rows = jnp.concatenate([int_x, int_c[:, None]], axis=1) * w_int[:, None]

    rows = jnp.concatenate([ev_rows, int_rows], axis=0)
    gram = rows.T @ rows
    spec_np = spectral_prior_matrix(m, cfg.m_start_frac, cfg.spec_kind)
    spec_w = cfg.alpha_spec / (s_hat**2 if norm else 1.0)
    # Traces without materialising a sum of two (M, M) matrices per pixel.
    trace = jnp.sum(jnp.diagonal(gram)[:m]) + spec_w * float(np.trace(spec_np))
    ridge = cfg.ridge * (trace / m + 1e-30)
    prior = spec_w * jnp.asarray(spec_np, dtype) + ridge * jnp.eye(m, dtype=dtype)
    if return_gram:
        return gram.at[:m, :m].add(prior), gram[:m, m], s_hat
    return gram[:m, :m] + prior, gram[:m, m], s_hat


def batch_system(
    rig,
    table,
    cfg,
    t_us,
    polarity,
    mask,
    column_offset_us,
    threshold_on,
    threshold_off,
    t0_phase_us,
    sweeps,
):
    """:func:`pixel_system` over a batch of pixels (leading axis), tables shared."""
    return jax.vmap(
        pixel_system, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0, None, None)
    )(
        rig,
        table,
        cfg,
        t_us,
        polarity,
        mask,
        column_offset_us,
        threshold_on,
        threshold_off,
        t0_phase_us,
        sweeps,
    )
