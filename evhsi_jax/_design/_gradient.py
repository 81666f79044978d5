"""The gradient used for design: pathwise where the error is smooth, likelihood-ratio
where it moves in integer steps.

The error of a reconstruction from events changes with the design in two ways: events
*move* (smooth: the implicit-function derivative of :mod:`._events` follows it through
the QP) and events *appear or vanish* (jumps). The count is governed by the threshold C
and the constant light c — lowering either adds events everywhere, the main way they
lower the error — and only negligibly by the band (FWHM) or the sweep (β, λ0, f,
through the refractory time). A pathwise derivative never sees a jump, so it
can miss the count effect of C and c (experiments/design_study.py compares both
estimators with finite differences of the exact pipeline).

So the loss is the *expected* error over the sensor's per-pixel threshold mismatch
and the constant light's non-uniformity, $F(θ) = E_z[\\,\\overline{e}(θ, z)]$ with
$C_p = C e^{σ_C z_{C,p}}$, $c_p = c e^{σ_c z_{c,p}}$ (both known to the
reconstruction), and

- $∂F/∂\\log C$, $∂F/∂\\log c$ by the antithetic likelihood-ratio (score-function)
  estimator $E[(\\bar e(+z) - \\bar e(-z))\\,z]/(2σ)$ per pixel — unbiased for
  $F$, jumps included (the density of $\\log C_p$ depends on $\\log C$, the pixel's
  error need not be continuous);
- the other four derivatives pathwise (autodiff through the events' implicit
  function, the QP's implicit VJP and the band table), averaged over $±z$;
- the hardware penalties by autodiff, the event count from the smooth existence
  weights of :mod:`._events` (its derivative matches finite differences of the exact
  count).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, Float, PRNGKeyArray

from ._objective import DesignProblem, design_loss
from ._space import PARAM_NAMES, DesignParams, constraint_values, penalty

__all__ = ["design_value_and_grad", "SCORE_PARAMS"]

#: Parameters whose error derivative comes from the likelihood-ratio estimator.
SCORE_PARAMS = ("threshold", "baseline_rel")


def _parts(problem: DesignProblem, u: DesignParams, z: Float[Array, "p 2"]):
    """Per-pixel errors at ±z, the log mean error and the penalty (all of u).

    The loss at +z and at −z is one evaluation of the training pixels taken twice
    (the second copy sees −z): one copy of the loss in the program instead of two.
    With the backward pass's two rows in one loop (:func:`design_value_and_grad`),
    the test suite's 3-spectrum problem (2026-12-07, float64, 2 cores) traced and
    compiled in 39 s instead of 59 s and ran in 0.38 s instead of 0.72 s; the
    values agree to ~1e-12 relative (another order of the same sums)."""
    params = problem.space.from_unconstrained(u)
    n = z.shape[0]
    twice = eqx.tree_at(
        lambda p: (p.spectra_fine, p.truth, p.columns),
        problem,
        tuple(
            jnp.concatenate([a, a])
            for a in (problem.spectra_fine, problem.truth, problem.columns)
        ),
    )
    _, a = design_loss(twice, params, jnp.concatenate([z, -z]))
    e = a["pixel_mse"]
    # Means over both copies: the averages of the two halves' means.
    mse = jnp.mean(e)
    n_mean = a["events_per_pixel"]
    rig = problem.rig(params)
    cons = constraint_values(params, n_mean, rig, problem.limits)
    pen = penalty(cons, problem.limits)
    aux = {
        "e_plus": e[:n],
        "e_minus": e[n:],
        "mse": mse,
        "events_per_pixel": n_mean,
        "exact_events_per_pixel": a["exact_events_per_pixel"],
        "truncated": a["truncated"],
        "constraints": cons,
        "penalty": pen,
    }
    return jnp.stack([jnp.log(mse), pen]), aux


def design_value_and_grad(
    problem: DesignProblem,
    u: DesignParams,
    *,
    key: PRNGKeyArray,
    score: bool = True,
):
    """The smoothed design loss and its gradient in the box's unconstrained space.

    **Arguments:**

    - `problem`: from :func:`design_problem`; `u`: unconstrained design
      (`problem.space.to_unconstrained`).
    - `key`: draws the jitter z (one per training pixel and quantity, antithetic).
    - `score`: use the likelihood-ratio estimator for C and c (False: pathwise for
      all six — for comparison).

    **Returns:** `(loss, grad, aux)` — $\\log \\bar e + $ penalty, its gradient
    (a :class:`DesignParams` of unconstrained derivatives), and `aux` with
    `log_mse`, `psnr_db`, `events_per_pixel`, `exact_events_per_pixel`,
    `event_rate_ev_s`, `truncated`, `constraints`, `penalty` and `grad_log_mse`
    (the error part of the gradient alone, without the penalties).
    """
    n = problem.truth.shape[0]
    z = jr.normal(key, (n, 2), problem.truth.dtype)
    values, vjp, aux = jax.vjp(lambda v: _parts(problem, v, z), u, has_aux=True)
    # Both rows of the Jacobian by one copy of the backward pass, run twice.
    rows = jax.lax.map(lambda c: vjp(c)[0], jnp.eye(2, dtype=values.dtype))
    g_err, g_pen = (jax.tree.map(lambda a, i=i: a[i], rows) for i in range(2))
    if score:
        diff = aux["e_plus"] - aux["e_minus"]
        repl = {}
        for name, col, spread in (
            ("threshold", 0, problem.threshold_spread),
            ("baseline_rel", 1, problem.light_spread),
        ):
            d_log = jnp.mean(diff * z[:, col]) / (2.0 * spread) / aux["mse"]
            # d log(param) / du of the sigmoid box (log scale for C and c).
            dlog_du = jax.grad(
                lambda v, name=name: jnp.log(
                    getattr(
                        problem.space.from_unconstrained(_with(u, name, v)),
                        name,
                    )
                )
            )(getattr(u, name))
            repl[name] = d_log * dlog_du
        g_err = DesignParams(*(repl.get(k, getattr(g_err, k)) for k in PARAM_NAMES))
    grad = jax.tree.map(jnp.add, g_err, g_pen)
    log_mse = values[0]
    params = problem.space.from_unconstrained(u)
    out = {
        "log_mse": log_mse,
        "psnr_db": -10.0 * log_mse / jnp.log(10.0),
        "events_per_pixel": aux["events_per_pixel"],
        "exact_events_per_pixel": aux["exact_events_per_pixel"],
        "event_rate_ev_s": aux["events_per_pixel"]
        * problem.limits.sensor_pixels
        * params.sweep_rate_hz,
        "truncated": aux["truncated"],
        "constraints": aux["constraints"],
        "penalty": aux["penalty"],
        "grad_log_mse": g_err,
    }
    return values[0] + values[1], grad, out


def _with(u: DesignParams, name: str, v) -> DesignParams:
    return DesignParams(*(v if k == name else getattr(u, k) for k in PARAM_NAMES))
