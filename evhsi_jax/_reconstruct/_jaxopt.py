"""The reference solvers from jaxopt (the only module that imports jaxopt).

jaxopt is in maintenance mode and warns on import; that one warning is filtered here.
Both solvers run per pixel and are vmapped by the caller; a vmapped `while_loop` runs
until the slowest pixel of the batch has converged (or `maxiter`).
"""

from __future__ import annotations

import warnings

import jax.numpy as jnp

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="JAXopt is no longer maintained")
    import jaxopt

__all__ = ["boxcdqp", "boxosqp"]


def boxcdqp(q_mat, q_vec, x0=None, *, maxiter: int = 500, tol: float = 1e-6):
    """jaxopt `BoxCDQP` (coordinate descent) on $\\min \\tfrac12 x^TQx + q^Tx$, x ≥ 0."""
    solver = jaxopt.BoxCDQP(maxiter=maxiter, tol=tol, implicit_diff=False)
    lower = jnp.zeros_like(q_vec)
    upper = jnp.full_like(q_vec, jnp.inf)
    init = jnp.zeros_like(q_vec) if x0 is None else jnp.maximum(x0, 0.0)
    return solver.run(
        init, params_obj=(q_mat, q_vec), params_ineq=(lower, upper)
    ).params


def boxosqp(q_mat, q_vec, x0=None, *, maxiter: int = 4000, tol: float = 1e-5):
    """jaxopt `BoxOSQP` (OSQP-style ADMM) with constraint matrix I, bounds [0, ∞)."""
    m = q_vec.shape[0]
    solver = jaxopt.BoxOSQP(maxiter=maxiter, tol=tol, implicit_diff=False)
    eye = jnp.eye(m, dtype=q_vec.dtype)
    lower = jnp.zeros_like(q_vec)
    upper = jnp.full_like(q_vec, jnp.inf)
    sol = solver.run(
        params_obj=(q_mat, q_vec), params_eq=eye, params_ineq=(lower, upper)
    )
    return jnp.maximum(sol.params.primal[0], 0.0)
