"""Box-constrained QP solvers for one pixel, $\\min_x \\tfrac12 x^TQx + q^Tx$, $x \\ge 0$.

Every solver here is written for one pixel and batched by the caller (vmap inside a
`lax.map` over fixed-size sub-batches, so each sub-batch's matrices stay in cache).

- :func:`apg` — accelerated projected gradient (FISTA) on the Jacobi-scaled problem,
  with gradient-based adaptive restart (O'Donoghue & Candès 2015) and a step from a power
  iteration; a fixed iteration budget (static), so a batch never waits for its slowest
  pixel.
- :func:`projected_newton` — a primal active-set method with exact Newton steps on the
  free variables (Cholesky); converges in a few iterations to the exact optimum.
- :func:`unconstrained` — the Cholesky solution without the bound (for the ablation).
- :func:`svd_nullvector` — the paper's baseline: the right singular vector of the
  augmented system with the smallest singular value, normalised by its last entry.
- :func:`kkt_residual` — the projected-gradient norm, 0 exactly at the optimum.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = [
    "apg",
    "projected_newton",
    "unconstrained",
    "svd_nullvector",
    "kkt_residual",
    "objective",
]


def objective(q_mat: Float[Array, "m m"], q_vec: Float[Array, " m"], x):
    """$\\tfrac12 x^TQx + q^Tx$."""
    return 0.5 * x @ (q_mat @ x) + q_vec @ x


def kkt_residual(q_mat, q_vec, x) -> Float[Array, ""]:
    """$\\|x - \\max(x - ∇f(x), 0)\\|_∞$ — zero iff x solves the box QP.

    Scaled by the largest diagonal entry of Q so it reads as a relative error in x.
    """
    g = q_mat @ x + q_vec
    scale = jnp.max(jnp.abs(jnp.diag(q_mat)))
    return jnp.max(jnp.abs(x - jnp.maximum(x - g / scale, 0.0)))


def _safe_sqrt_diag(q_mat):
    d = jnp.diag(q_mat)
    return jnp.sqrt(jnp.maximum(d, 1e-30 + 1e-12 * jnp.max(d)))


def apg(
    q_mat: Float[Array, "m m"],
    q_vec: Float[Array, " m"],
    x0: Float[Array, " m"] | None = None,
    *,
    iters: int = 100,
    power_iters: int = 12,
) -> Float[Array, " m"]:
    """Accelerated projected gradient with adaptive restart.

    Works on $y = \\sqrt{\\mathrm{diag}\\,Q}\\,x$ (unit diagonal; the bound $y \\ge 0$ is
    unchanged), with step $1/L$, $L$ = 1.1 × a power-iteration estimate of
    $λ_{max}$. Momentum is reset whenever the last step went against the gradient.

    **Arguments:**

    - `q_mat`, `q_vec`: the problem, shapes `(m, m)` (symmetric positive definite) and
      `(m,)`.
    - `x0`: warm start (clipped to ≥ 0); default zeros.
    - `iters`: iterations (static).
    - `power_iters`: power-iteration steps for $L$ (static).

    **Returns:** x, shape `(m,)`, ≥ 0.
    """
    d = _safe_sqrt_diag(q_mat)
    qs = q_mat / d[:, None] / d[None, :]
    gs = q_vec / d

    def power(_, v):
        w = qs @ v
        return w / jnp.maximum(jnp.linalg.norm(w), 1e-30)

    v0 = jnp.ones_like(gs) + 0.01 * jnp.arange(gs.shape[0], dtype=gs.dtype)
    v = jax.lax.fori_loop(0, power_iters, power, v0 / jnp.linalg.norm(v0))
    lip = 1.1 * jnp.maximum(v @ (qs @ v), 1e-30)
    step = 1.0 / lip
    y0 = jnp.zeros_like(gs) if x0 is None else jnp.maximum(x0, 0.0) * d

    def body(_, state):
        y, z, t = state
        g = qs @ z + gs
        y_new = jnp.maximum(z - step * g, 0.0)
        restart = g @ (y_new - y) > 0
        t_new = 0.5 * (1.0 + jnp.sqrt(1.0 + 4.0 * t * t))
        mom = jnp.where(restart, 0.0, (t - 1.0) / t_new)
        z_new = y_new + mom * (y_new - y)
        return y_new, z_new, jnp.where(restart, 1.0, t_new)

    one = jnp.ones((), gs.dtype)
    y, _, _ = jax.lax.fori_loop(0, iters, body, (y0, y0, one))
    return y / d


def unconstrained(q_mat, q_vec) -> Float[Array, " m"]:
    """$-Q^{-1}q$ by Cholesky (no bound)."""
    c = jax.scipy.linalg.cho_factor(q_mat, lower=True)
    return -jax.scipy.linalg.cho_solve(c, q_vec)


def _free_solve(q_mat, q_vec, free):
    """Minimise over the free variables with the others fixed at 0."""
    f = free.astype(q_mat.dtype)
    q_red = q_mat * f[:, None] * f[None, :] + jnp.diag(1.0 - f) * jnp.max(
        jnp.diag(q_mat)
    )
    c = jax.scipy.linalg.cho_factor(q_red, lower=True)
    return -jax.scipy.linalg.cho_solve(c, q_vec * f) * f


def projected_newton(
    q_mat: Float[Array, "m m"],
    q_vec: Float[Array, " m"],
    x0: Float[Array, " m"] | None = None,
    *,
    iters: int = 6,
) -> Float[Array, " m"]:
    """Primal active-set iterations with exact Newton steps on the free set.

    Each iteration: the free set is {x > 0} ∪ {gradient < 0}; solve the QP restricted
    to it exactly (Cholesky); move from x towards that point as far as the bound allows,
    stopping at the first variable that reaches 0 (which leaves the free set). From a
    feasible start the objective never increases; at a fixed point the KKT conditions
    hold. `iters` (static) bounds the work.
    """
    x = jnp.zeros_like(q_vec) if x0 is None else jnp.maximum(x0, 0.0)

    def body(_, x):
        g = q_mat @ x + q_vec
        free = (x > 0) | (g < 0)
        target = _free_solve(q_mat, q_vec, free)
        delta = target - x
        # Largest step in [0, 1] keeping the positive variables ≥ 0; variables at 0
        # that the subspace step would push negative are held at 0 (projected).
        shrinking = (delta < 0) & (x > 0)
        ratio = jnp.where(shrinking, x / jnp.where(shrinking, -delta, 1.0), jnp.inf)
        s = jnp.minimum(1.0, jnp.min(ratio))
        x_new = jnp.maximum(x + s * delta, 0.0)
        # The variable(s) that block the step are set exactly to 0.
        return jnp.where(shrinking & (ratio <= s), 0.0, x_new)

    return jax.lax.fori_loop(0, iters, body, x)


def svd_nullvector(gram_aug: Float[Array, "m1 m1"]) -> Float[Array, " m"]:
    """The paper's unconstrained baseline (Eq. 15).

    The eigenvector of $\\hat N^T \\hat N$ with the smallest eigenvalue (= the right
    singular vector of $\\hat N$ with the smallest singular value), scaled so its last
    (constant-light) entry is 1. A vector whose last entry vanishes has no finite
    answer: zeros are returned there.
    """
    _, vecs = jnp.linalg.eigh(gram_aug)
    v = vecs[:, 0]
    last = v[-1]
    ok = jnp.abs(last) > 1e-12 * jnp.max(jnp.abs(v))
    return jnp.where(ok, v[:-1] / jnp.where(ok, last, 1.0), 0.0)


def active_set_batch(
    q_mat: Float[Array, "b m m"],
    q_vec: Float[Array, "b m"],
    *,
    tol: float = 1e-5,
    max_iters: int = 20,
):
    """Exact box-QP solutions for a small batch: Cholesky, then active-set steps only
    where needed.

    1. The unconstrained minimiser $-Q^{-1}q$ (one Cholesky per pixel). Where it is
       ≥ 0 it is the answer — most pixels of natural scenes.
    2. Only if some pixel of the batch violates the bound (or the KKT test at
       `tol`), :func:`projected_newton`-style steps run on the whole batch, starting
       from the clipped solution, until every pixel passes the KKT test or
       `max_iters` steps were taken. Inside `lax.map` this is a real branch: batches
       without a violation skip it.

    **Returns:** `(x, kkt, steps)` — solutions `(b, m)`, KKT residuals `(b,)` and the
    number of active-set steps this batch took.
    """
    x_u = jax.vmap(unconstrained)(q_mat, q_vec)
    x = jnp.maximum(x_u, 0.0)
    kkt = jax.vmap(kkt_residual)(q_mat, q_vec, x)

    def step(x):
        return jax.vmap(lambda a, b, x: projected_newton(a, b, x, iters=1))(
            q_mat, q_vec, x
        )

    def cond(state):
        _, kkt, it = state
        return (it < max_iters) & jnp.any(kkt > tol)

    def body(state):
        x, _, it = state
        x = step(x)
        return x, jax.vmap(kkt_residual)(q_mat, q_vec, x), it + 1

    x, kkt, it = jax.lax.while_loop(cond, body, (x, kkt, jnp.zeros((), jnp.int32)))
    return x, kkt, it
