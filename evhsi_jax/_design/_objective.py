"""The design loss: expected reconstruction error on training reflectances + penalties.

$\\mathcal L(θ) = \\log \\overline{\\mathrm{MSE}}(θ) + ρ \\sum_i \\max(0, g_i(θ) + m)^2$

- $\\overline{\\mathrm{MSE}}$: mean over the training pixels of the squared error of the
  reconstructed channel reflectances (PSNR $= -10\\log_{10}\\overline{\\mathrm{MSE}}$),
  each pixel simulated for one sweep (known thresholds, no mismatch: the design
  question is what the optics allow, not how well thresholds are calibrated) and
  reconstructed by the library's per-pixel QP (`pixel_system`, implicit-differentiation
  `box_qp`), with events from `_soft_events` (structure held, times by the implicit function
  theorem, smooth existence of marginal events).
- $g_i$: the hardware limits of :mod:`._space`; the event rate comes from the soft event
  model (:func:`~evhsi_jax.forward.soft_event_counts`, temperature 0.002: ±1 % of the exact
  count on the training set, where 0.01 already over-counts by ~15 %), the mean
  expected events per training pixel and sweep scaled to the full sensor:
  $R = \\bar n \\cdot 1280 \\cdot 720 \\cdot f$ — as if the training reflectances filled
  the field of view in equal shares.

**Training set.** The `tcs` test-colour samples (44 spectra, disjoint from the
ColorChecker) at several brightness gains. A spectrum's error as a function of the
design is a staircase of many small jumps (events appear and vanish); scaling the
reflectance shifts its log trace against the threshold lattice, so the gains average
the jumps out the way shading does in a real scene.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._model import Rig, band_table, load_scene, lookup, soft_event_counts
from .._reconstruct import ProblemConfig, box_qp
from ._soft_events import (
    StructureConfig,
    band_grid,
    hard_events,
    pixel_qp,
    pixel_traces,
    sg,
)
from ._space import (
    DesignLimits,
    DesignParams,
    DesignSpace,
    constraint_values,
    event_rate_ev_s,
    penalty,
)

__all__ = ["DesignProblem", "design_problem", "design_loss", "training_spectra"]

DEFAULT_GAINS = (1.0, 0.8, 0.64, 0.51)


def training_spectra(
    scene: str = "tcs",
    gains=DEFAULT_GAINS,
    *,
    rig: Rig | None = None,
    limit: int | None = None,
):
    """Training reflectances: a scene's palette at each brightness gain.

    **Returns:** `(fine, truth)` — on the rig's fine grid `(p, F)` and averaged per
    channel `(p, M)`, float64 NumPy, `p = len(gains) × palette size` (or `limit`
    spectra, spread evenly over the palette, per gain).
    """
    rig = rig or Rig()
    sc = load_scene(scene)
    pal_fine = sc.palette_on(rig.grid.fine_edges_nm)
    pal_ch = sc.palette_on(rig.grid.edges_nm)
    if limit is not None:
        pick = np.unique(
            np.linspace(0, pal_fine.shape[0] - 1, limit).round().astype(int)
        )
        pal_fine, pal_ch = pal_fine[pick], pal_ch[pick]
    gains = [float(g) for g in gains]
    if not gains or min(gains) <= 0 or max(gains) > 1:
        raise ValueError("brightness gains must lie in (0, 1]")
    fine = np.concatenate([g * pal_fine for g in gains])
    truth = np.concatenate([g * pal_ch for g in gains])
    return fine, truth


def _n_steps(base: Rig, space: DesignSpace, cap: int) -> int:
    """Grid steps so that a step of the slowest sweep in the box is ≤ refractory."""
    speed_min = space.beta_nm_per_rad[0] * math.pi * space.sweep_rate_hz[0] * 1e-6
    span = (base.grid.stop_nm - base.grid.start_nm) + 6.0 * space.fwhm_nm[1]
    n = math.ceil(span / (speed_min * float(base.refractory_us)))
    n = 256 * math.ceil(n / 256)
    if n > cap:
        raise ValueError(
            f"the design box needs {n} time steps (its slowest sweep moves the band "
            f"{speed_min * float(base.refractory_us):.3f} nm per refractory period); "
            f"raise the lower sweep-rate or β bound, or max_steps (now {cap})"
        )
    return n


class DesignProblem(eqx.Module):
    """A design problem: training pixels, base rig, box, limits and settings.

    Build with :func:`design_problem`; evaluate with :func:`design_loss` (or call it).
    Arrays are leaves; everything else is static.
    """

    spectra_fine: Float[Array, "p f"]
    truth: Float[Array, "p m"]
    columns: Int[Array, " p"]
    base_rig: Rig
    space: DesignSpace = eqx.field(static=True)
    limits: DesignLimits = eqx.field(static=True)
    structure: StructureConfig = eqx.field(static=True)
    config: ProblemConfig = eqx.field(static=True)
    soft_temperature: float = eqx.field(static=True)
    threshold_spread: float = eqx.field(static=True)
    light_spread: float = eqx.field(static=True)

    def rig(self, params: DesignParams) -> Rig:
        """The base rig with the design's parameters."""
        return params.to_rig(self.base_rig)

    def __call__(self, params: DesignParams):
        return design_loss(self, params)


def design_problem(
    scene: str = "tcs",
    gains=DEFAULT_GAINS,
    *,
    base_rig: Rig | None = None,
    space: DesignSpace | None = None,
    limits: DesignLimits | None = None,
    config: ProblemConfig | None = None,
    spectra_limit: int | None = None,
    max_events: int = 96,
    smoothing: float = 0.01,
    weighted_rows: bool = True,
    soft_temperature: float = 0.0,
    threshold_spread: float = 0.067,
    light_spread: float = 0.1,
    max_steps: int = 32768,
) -> DesignProblem:
    """Set up a design problem on a training scene.

    **Arguments:**

    - `scene`, `gains`, `spectra_limit`: training reflectances (:func:`training_spectra`).
    - `base_rig`: what the design does not change (channels, refractory, D, E, ε);
      default the paper rig without threshold mismatch. Its dtype is the problem's.
    - `space`, `limits`: the search box and the hardware limits.
    - `config`: the reconstruction's weights (default: the library defaults with cubic
      table interpolation, so derivatives in β and λ0 are continuous).
    - `max_events`: event slots per training pixel; `smoothing`: T of the existence
      weights (0: held-fixed structure, pure implicit-function gradient);
      `soft_temperature`: of the soft event model behind the event rate.
    - `threshold_spread`, `light_spread`: relative per-pixel spreads of C and c for
      the jittered loss (:func:`design_loss`'s `jitter`): 0.067 is the paper's
      C ~ N(0.15, 0.01); 10 % non-uniformity of the constant light is an assumption.
    - `max_steps`: cap on the time grid (its size follows from the box: a step must
      not exceed the refractory time at the slowest sweep).
    """
    base_rig = base_rig or Rig(threshold_sigma=0.0)
    space = space or DesignSpace()
    limits = limits or DesignLimits()
    config = config or ProblemConfig(lookup_order=3)
    if smoothing <= 0 or soft_temperature < 0:
        raise ValueError("smoothing must be > 0 and soft_temperature >= 0")
    if threshold_spread < 0 or light_spread < 0:
        raise ValueError("threshold_spread and light_spread must be >= 0")
    fine, truth = training_spectra(scene, gains, rig=base_rig, limit=spectra_limit)
    p = fine.shape[0]
    width = 1280
    # Columns spread over the sensor: they only shift each pixel's timestamp phase.
    cols = np.linspace(0, width - 1, p).round().astype(np.int32)
    dtype = base_rig.fwhm_nm.dtype
    return DesignProblem(
        spectra_fine=jnp.asarray(fine, dtype),
        truth=jnp.asarray(truth, dtype),
        columns=jnp.asarray(cols),
        base_rig=base_rig,
        space=space,
        limits=limits,
        structure=StructureConfig(
            n_steps=_n_steps(base_rig, space, max_steps),
            max_events=max_events,
            smoothing=smoothing,
            weighted_rows=weighted_rows,
            width=width,
        ),
        config=config,
        soft_temperature=soft_temperature,
        threshold_spread=float(threshold_spread),
        light_spread=float(light_spread),
    )


def design_loss(
    problem: DesignProblem,
    params: DesignParams,
    jitter: Float[Array, "p 2"] | None = None,
):
    """The design loss and its parts (differentiable in `params`).

    **Arguments:**

    - `problem`, `params`: the problem and the design.
    - `jitter`: standard-normal draws `(z_C, z_c)` per training pixel: pixel p sees
      threshold $C e^{σ_C z_{C,p}}$ and constant light $c e^{σ_c z_{c,p}}$ (the
      sensor's threshold mismatch and the panel's non-uniformity, both known to the
      reconstruction); None: every pixel sees the nominal values.

    **Returns:** `(loss, aux)` with `aux` holding `log_mse`, `psnr_db`,
    `pixel_mse` `(p,)`, `events_per_pixel` (smooth count, per sweep),
    `exact_events_per_pixel` (held structure), `event_rate_ev_s`, `truncated`
    (pixels with more events than slots), `constraints` (dict, feasible ≤ 0),
    `penalty` and, with `soft_temperature` > 0, `soft_model_events_per_pixel`.
    """
    rig = problem.rig(params)
    scfg = problem.structure
    dtype = rig.fwhm_nm.dtype
    n_pix = problem.truth.shape[0]
    thr = 0.5 * (rig.threshold_on + rig.threshold_off)
    if jitter is None:
        thr_p = jnp.full((n_pix,), thr, dtype)
        c_p = jnp.full((n_pix,), rig.baseline_rel, dtype)
    else:
        jitter = jnp.asarray(jitter, dtype)
        thr_p = thr * jnp.exp(problem.threshold_spread * jitter[:, 0])
        c_p = rig.baseline_rel * jnp.exp(problem.light_spread * jitter[:, 1])
    traces = pixel_traces(rig, problem.spectra_fine, scfg.fwhm_bound_nm)
    channel_table = band_table(rig, fwhm_bound_nm=scfg.fwhm_bound_nm).channels(
        rig.grid.sub
    )
    lam, t_local = band_grid(rig, scfg.n_steps)
    log_i = jnp.log(
        jnp.maximum(lookup(traces, lam), 0.0) + (c_p + rig.log_eps)[None, :]
    )  # (n+1, p)
    step, t_cross, pol, mask, count = hard_events(
        log_i, t_local, thr_p, rig.refractory_us, scfg.max_events
    )
    offsets = rig.column_offsets(scfg.width)[problem.columns]

    def one(trace_col, log_col, st, tc, pl, mk, off, thr_1, c_1):
        rig_p = rig.with_leaves(
            threshold_on=thr_1, threshold_off=thr_1, baseline_rel=c_1
        )
        return pixel_qp(
            rig_p,
            channel_table,
            trace_col,
            traces.lo_nm,
            traces.step_nm,
            problem.config,
            scfg,
            lam,
            t_local,
            log_col,
            st,
            tc,
            pl,
            mk,
            off,
        )

    q_mat, q_vec, smooth_n = jax.vmap(one)(
        traces.values.T, log_i.T, step, t_cross, pol, mask, offsets, thr_p, c_p
    )
    # One pixel per step (`lax.map`), not a batched while-loop with batched Cholesky:
    # the vmapped form stalled inside XLA's CPU runtime in full-size design runs
    # (all worker threads idle). The training sets are small, so this costs little.
    x = jax.lax.map(lambda a: box_qp(*a), (q_mat, q_vec))
    pixel_mse = jnp.mean(jnp.square(x - problem.truth), axis=1)
    mse = jnp.mean(pixel_mse)
    log_mse = jnp.log(mse)

    smooth_mean = jnp.mean(smooth_n)
    cons = constraint_values(params, smooth_mean, rig, problem.limits)
    pen = penalty(cons, problem.limits)
    aux = {
        "log_mse": log_mse,
        "psnr_db": -10.0 * log_mse / jnp.log(10.0),
        "pixel_mse": pixel_mse,
        "events_per_pixel": smooth_mean,
        "exact_events_per_pixel": jnp.mean(count.astype(dtype)),
        "event_rate_ev_s": event_rate_ev_s(
            smooth_mean, params.sweep_rate_hz, problem.limits
        ),
        "truncated": jnp.sum(count > scfg.max_events),
        "constraints": cons,
        "penalty": pen,
    }
    if problem.soft_temperature > 0:
        # The per-step soft model, as a cross-check of the count (value only: its
        # gradients explode at temperatures low enough for an unbiased count).
        on, off = soft_event_counts(
            sg(log_i),
            sg(t_local),
            sg(thr_p),
            sg(thr_p),
            sg(rig.refractory_us),
            temperature=problem.soft_temperature,
        )
        aux["soft_model_events_per_pixel"] = jnp.mean(jnp.sum(on + off, axis=0))
    return log_mse + pen, aux
