"""Non-negative least squares for many right-hand sides that share one Gram matrix."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["nonneg_lsq_shared"]


@functools.partial(jax.jit, static_argnames="iters")
def nonneg_lsq_shared(
    q_mat: Float[Array, "wl wl"], q_vec: Float[Array, "n wl"], *, iters: int
) -> Float[Array, "n wl"]:
    """$\\min_{x \\ge 0} ½x^TQx - q^Tx$ for every row of `q_vec`, one shared Q (ADMM).

    Jacobi-scaled first ($x = D y$, $D = \\mathrm{diag}(Q)^{-1/2}$, which keeps the
    bound $y \\ge 0$): the red channels, weakly lit through D(λ)E(λ), otherwise worsen
    Q's condition number ~$10^4$-fold. ADMM splits $y = z$, $z \\ge 0$; its y-update
    uses the one shared inverse $(Q + ρI)^{-1}$, so an iteration is a matrix product
    over all rows. ρ = $\\sqrt{λ_{min} λ_{max}}$ of the scaled Q (Ghadimi et al. 2015).
    Returns the feasible iterate z.
    """
    diag = jnp.diag(q_mat)
    # A channel the data never see (zero diagonal) is held at 0 rather than divided by 0.
    d = jnp.where(diag > 0, jax.lax.rsqrt(jnp.where(diag > 0, diag, 1.0)), 0.0)
    qs = q_mat * d[:, None] * d[None, :]
    bs = q_vec * d
    ev = jnp.linalg.eigvalsh(qs)
    rho = jnp.sqrt(jnp.maximum(ev[0], 1e-6 * ev[-1]) * ev[-1])
    m = qs.shape[0]
    inv = jnp.linalg.inv(qs + rho * jnp.eye(m, dtype=qs.dtype))

    def body(_, carry):
        z, u = carry
        y = (bs + rho * (z - u)) @ inv
        z = jnp.maximum(y + u, 0.0)
        return z, u + y - z

    zero = jnp.zeros_like(bs)
    z, _ = jax.lax.fori_loop(0, iters, body, (zero, zero))
    return z * d
