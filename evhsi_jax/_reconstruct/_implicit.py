"""Differentiable reconstruction: the box-QP solution map with an implicit VJP.

At the solution $x^\\star$ of $\\min \\tfrac12 x^TQx + q^Tx$, $x \\ge 0$, with free set
$F = \\{x_i > 0\\}$, the KKT conditions on $F$ read $Q_{FF}x_F + q_F = 0$ (and $x_A = 0$).
Differentiating, $dx_F = -Q_{FF}^{-1}(dQ_{FF}x_F + dq_F)$, $dx_A = 0$. For a cotangent
$\\bar x$, with $u$ solving $Q_{FF}u_F = \\bar x_F$ ($u_A = 0$):
$\\bar q = -u$ and $\\bar Q = -u x^T$. No solver iterations are differentiated.
At a degenerate point (some $x_i = 0$ with zero gradient) the map is not differentiable;
the variable is treated as active there.

:func:`reconstruct_pixels` chains this with the per-pixel assembly, so the cube is a
differentiable function of the rig's leaves (β, FWHM, τx, thresholds, c, D, E) for the
design studies.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._model import Rig, band_table
from ._pixels import PixelEvents
from ._problem import ProblemConfig, pixel_system
from ._solvers import active_set, cho_factor, reduced

__all__ = ["box_qp", "reconstruct_pixels"]

_ACTIVE_SET_STEPS = 24


def _forward(q_mat, q_vec):
    return active_set(q_mat, q_vec, iters=_ACTIVE_SET_STEPS, robust=True)


@jax.custom_vjp
def box_qp(q_mat: Float[Array, "m m"], q_vec: Float[Array, " m"]) -> Float[Array, " m"]:
    """The solution of one box QP (x ≥ 0), differentiable by the implicit function
    theorem (see the module docstring)."""
    return _forward(q_mat, q_vec)


def _fwd(q_mat, q_vec):
    x = _forward(q_mat, q_vec)
    return x, (q_mat, x)


def _bwd(res, x_bar):
    q_mat, x = res
    free = (x > 0).astype(q_mat.dtype)
    c = cho_factor(reduced(q_mat, x > 0), robust=True)
    u = jax.scipy.linalg.cho_solve(c, x_bar * free) * free
    return -jnp.outer(u, x), -u


box_qp.defvjp(_fwd, _bwd)


def reconstruct_pixels(
    rig: Rig,
    t_us: Float[Array, "n k"],
    polarity,
    mask,
    columns,
    *,
    width: int,
    sweeps: int = 1,
    config: ProblemConfig | None = None,
    threshold_on=None,
    threshold_off=None,
    fwhm_bound_nm: float | None = None,
) -> Float[Array, "n m"]:
    """Spectra of a batch of pixels as a differentiable function of the rig.

    **Arguments:**

    - `rig`: the rig whose leaves are differentiated (e.g. with `eqx.filter_grad`).
    - `t_us`, `polarity`, `mask`: padded per-pixel event lists `(n, k)` (times relative
      to the recording start at sweep phase 0, ±1, real-event mask), e.g. from
      `group_pixels`.
    - `columns`: pixel columns `(n,)` (int); `width`: sensor width (for τx).
    - `sweeps`: sweeps spanned (static); `config`: problem weights (default: the
      defaults with cubic table interpolation, so derivatives in β, τx, λ0 are smooth).
    - `threshold_on`, `threshold_off`: per-pixel thresholds `(n,)`; default the rig's.
    - `fwhm_bound_nm`: static bound on the FWHM when it is being differentiated.

    **Returns:** x, shape `(n, M)`.
    """
    cfg = config or ProblemConfig(lookup_order=3)
    table = band_table(rig, fwhm_bound_nm=fwhm_bound_nm).channels(rig.grid.sub)
    offsets = rig.column_offsets(width)[columns]
    n = t_us.shape[0]
    dtype = table.values.dtype
    thr_on = (
        jnp.full((n,), rig.threshold_on, dtype)
        if threshold_on is None
        else threshold_on
    )
    thr_off = (
        jnp.full((n,), rig.threshold_off, dtype)
        if threshold_off is None
        else threshold_off
    )

    def one(px):
        q_mat, q_vec, _ = pixel_system(rig, table, cfg, px, sweeps)
        return box_qp(q_mat, q_vec)

    px = PixelEvents.batch(t_us, polarity, mask, offsets, thr_on, thr_off, 0.0)
    return jax.vmap(one)(px)
