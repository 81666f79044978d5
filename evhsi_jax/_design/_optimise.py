"""Gradient descent on the design loss (optax Adam in the box's unconstrained space)."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._base import atomic_write
from ._gradient import design_value_and_grad
from ._objective import DesignProblem
from ._space import DesignParams

__all__ = ["DesignResult", "optimise_design", "save_trajectory"]


@dataclasses.dataclass(frozen=True)
class DesignResult:
    """The outcome of :func:`optimise_design`.

    - `params`: the final design (the average of the last `average` iterates in the
      unconstrained space — the likelihood-ratio gradient is noisy).
    - `initial`: the starting design.
    - `trajectory`: one dict per step: `step`, `loss`, `log_mse`, `psnr_db`,
      `events_per_pixel`, `event_rate_ev_s`, `penalty`, `constraints`, `params`,
      `grad` (unconstrained), `seconds` since the start.
    - `seconds`: wall time.
    """

    params: DesignParams
    initial: DesignParams
    trajectory: list
    seconds: float


def _record(step, loss, aux, params, grad_u, t0):
    return {
        "step": step,
        "loss": float(loss),
        "log_mse": float(aux["log_mse"]),
        "psnr_db": float(aux["psnr_db"]),
        "events_per_pixel": float(aux["events_per_pixel"]),
        "exact_events_per_pixel": float(aux["exact_events_per_pixel"]),
        "event_rate_ev_s": float(aux["event_rate_ev_s"]),
        "penalty": float(aux["penalty"]),
        "constraints": {k: float(v) for k, v in aux["constraints"].items()},
        "params": params.as_dict(),
        "grad": grad_u.as_dict(),
        "seconds": time.perf_counter() - t0,
    }


def optimise_design(
    problem: DesignProblem,
    init: DesignParams | None = None,
    *,
    steps: int = 100,
    learning_rate: float = 0.05,
    final_learning_rate: float | None = None,
    clip_norm: float | None = 1.0,
    average: int = 10,
    print_every: int | None = 10,
    callback: Callable[[dict], None] | None = None,
    score: bool = True,
    key=None,
) -> DesignResult:
    """Minimise :func:`design_loss` with Adam over the unconstrained box coordinates.

    Every iterate is inside the box (sigmoid reparametrisation); the hardware limits
    are penalties. The loss and its gradient are one compiled function.

    **Arguments:**

    - `problem`: from :func:`design_problem`.
    - `init`: start (default: the base rig's design, clipped into the box).
    - `steps`, `learning_rate`: Adam's budget and step in unconstrained units (0.05 ≈
      1 % of a box's width per step near its middle).
    - `final_learning_rate`: if given, the step decays along a cosine from
      `learning_rate` to it over `steps` (default: constant).
    - `clip_norm`: the gradient is clipped to this global norm before Adam (None: no
      clipping). Without it the penalty gradients of an infeasible start (~1e4)
      fill Adam's second-moment estimate, which then hides the error gradient (~0.1–1)
      for hundreds of steps while the momentum of the penalty keeps pushing past the
      constraint (seen: C and c overshot, training PSNR 27 → 24 dB).
    - `average`: the result averages the last `average` iterates (≥ 1).
    - `print_every`: progress line every so many steps (None: silent).
    - `callback`: called with each step's record.
    - `score`, `key`: the gradient estimator (:func:`design_value_and_grad`; a fresh
      jitter draw per step from `key`, default `jax.random.key(0)`).
    """
    space = problem.space
    init = init if init is not None else DesignParams.from_rig(problem.base_rig)
    dtype = problem.base_rig.fwhm_nm.dtype
    u = jax.tree.map(lambda v: jnp.asarray(v, dtype), space.to_unconstrained(init))
    init = space.from_unconstrained(u)

    @eqx.filter_jit
    def value_and_grad(u, problem, k):
        return design_value_and_grad(problem, u, key=k, score=score)

    key = jax.random.key(0) if key is None else key
    lr = (
        learning_rate
        if final_learning_rate is None
        else optax.cosine_decay_schedule(
            learning_rate, max(steps, 1), final_learning_rate / learning_rate
        )
    )
    opt = optax.adam(lr)
    if clip_norm is not None:
        opt = optax.chain(optax.clip_by_global_norm(clip_norm), opt)

    @jax.jit
    def step_fn(g, state, u):
        # optax mixes Python floats with its int32 step count (`b1 ** count`), which
        # strict dtype promotion (our tests) rejects: allow standard promotion here.
        with jax.numpy_dtype_promotion("standard"):
            updates, state = opt.update(g, state, u)
            return optax.apply_updates(u, updates), state

    state = opt.init(u)
    trajectory, tail = [], []
    t0 = time.perf_counter()
    for step in range(steps + 1):
        key, sub = jax.random.split(key)
        loss, g, aux = value_and_grad(u, problem, sub)
        params = space.from_unconstrained(u)
        rec = _record(step, loss, aux, params, g, t0)
        trajectory.append(rec)
        if callback is not None:
            callback(rec)
        if print_every and (step % print_every == 0 or step == steps):
            p = rec["params"]
            print(
                f"step {step:4d}  loss {rec['loss']:8.4f}  PSNR {rec['psnr_db']:6.2f} dB  "
                f"events/px {rec['events_per_pixel']:6.2f}  "
                f"rate {rec['event_rate_ev_s'] / 1e6:7.2f} Mev/s  "
                f"FWHM {p['fwhm_nm']:5.2f}  β {p['beta_nm_per_rad']:6.1f}  "
                f"λ0 {p['sweep_start_nm']:6.1f}  c {p['baseline_rel']:.4f}  "
                f"C {p['threshold']:.4f}  f {p['sweep_rate_hz']:5.2f}  "
                f"({rec['seconds']:.0f} s)",
                flush=True,
            )
        if not np.isfinite(rec["loss"]) or not all(
            np.isfinite(v) for v in rec["grad"].values()
        ):
            raise FloatingPointError(
                f"non-finite design loss or gradient at step {step}"
            )
        if step >= steps - max(average, 1) + 1:
            tail.append(u)
        if step == steps:
            break
        u, state = step_fn(g, state, u)
    u_avg = jax.tree.map(lambda *v: jnp.mean(jnp.stack(v), axis=0), *tail)
    return DesignResult(
        params=space.from_unconstrained(u_avg),
        initial=init,
        trajectory=trajectory,
        seconds=time.perf_counter() - t0,
    )


def save_trajectory(path: str | os.PathLike, result: DesignResult, **extra) -> None:
    """Write the result (initial and final design, every step) as JSON, atomically."""
    payload = {
        **extra,
        "initial": result.initial.as_dict(),
        "final": result.params.as_dict(),
        "seconds": result.seconds,
        "trajectory": result.trajectory,
    }
    text = json.dumps(payload, indent=1) + "\n"
    atomic_write(path, lambda f: f.write(text.encode()))
