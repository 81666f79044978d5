"""Box-QP solvers against an independent SciPy reference, KKT, and implicit gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import nnls

from evhsi_jax._reconstruct import _solvers
from evhsi_jax._reconstruct._implicit import box_qp
from evhsi_jax._reconstruct._jaxopt import boxcdqp, boxosqp

M = 12


def _problem(kind: str, seed: int):
    """Q = NᵀN + ridge with a known conditioning; q chosen so some bounds are active."""
    rng = np.random.default_rng(seed)
    if kind == "random":
        n = rng.standard_normal((3 * M, M))
        q_mat = n.T @ n + 0.1 * np.eye(M)
    elif kind == "ill":  # smooth (low-frequency dominated), condition ~1e6
        u, _ = np.linalg.qr(rng.standard_normal((M, M)))
        q_mat = u @ np.diag(np.logspace(0, 6, M)) @ u.T
    else:  # "banded": a narrow-band-like tridiagonal-ish Gram
        a = np.zeros((2 * M, M))
        for r in range(2 * M):
            c = r // 2
            a[r, max(c - 1, 0) : c + 2] = rng.uniform(
                0.2, 1.0, min(c + 2, M) - max(c - 1, 0)
            )
        q_mat = a.T @ a + 1e-3 * np.eye(M)
    q_mat = 0.5 * (q_mat + q_mat.T)
    x_true = np.maximum(rng.standard_normal(M), 0.0)  # about half the bounds active
    q_vec = -q_mat @ x_true + np.where(x_true == 0, rng.uniform(0.1, 1.0, M), 0.0)
    return q_mat, q_vec


def _reference(q_mat, q_vec):
    # ½xᵀQx + qᵀx = ½‖Lᵀx + L⁻¹q‖² + const, so NNLS on (Lᵀ, −L⁻¹q) solves the box QP.
    chol = np.linalg.cholesky(q_mat)
    x, _ = nnls(chol.T, -np.linalg.solve(chol, q_vec), maxiter=10_000)
    return x


CASES = [(k, s) for k in ("random", "ill", "banded") for s in (0, 1)]


@pytest.mark.parametrize("kind,seed", CASES)
@pytest.mark.parametrize("solver", ["active_set_batch", "active_set", "boxcdqp"])
def test_exact_solvers_match_scipy(kind, seed, solver):
    with jax.enable_x64(True):
        q_mat, q_vec = _problem(kind, seed)
        ref = _reference(q_mat, q_vec)
        qj, vj = jnp.asarray(q_mat), jnp.asarray(q_vec)
        if solver == "active_set_batch":
            x, kkt, _ = _solvers.active_set_batch(qj[None], vj[None], tol=1e-10)
            x = x[0]
        elif solver == "active_set":
            x = _solvers.active_set(qj, vj, iters=4 * M)
        else:
            x = boxcdqp(qj, vj, maxiter=20_000, tol=1e-12)
        x = np.asarray(x)
        scale = np.abs(ref).max()
        assert np.all(x >= 0)
        np.testing.assert_allclose(
            x,
            ref,
            atol=1e-6 * scale * (1e3 if kind == "ill" and solver == "boxcdqp" else 1),
        )


@pytest.mark.parametrize("kind,seed", [("random", 0), ("banded", 1)])
def test_first_order_solvers_match_scipy_when_well_conditioned(kind, seed):
    with jax.enable_x64(True):
        q_mat, q_vec = _problem(kind, seed)
        ref = _reference(q_mat, q_vec)
        x_apg = np.asarray(
            _solvers.apg(jnp.asarray(q_mat), jnp.asarray(q_vec), iters=3000)
        )
        x_osqp = np.asarray(
            boxosqp(jnp.asarray(q_mat), jnp.asarray(q_vec), tol=1e-9, maxiter=20_000)
        )
        scale = np.abs(ref).max()
        np.testing.assert_allclose(x_apg, ref, atol=1e-5 * scale)
        np.testing.assert_allclose(x_osqp, ref, atol=1e-3 * scale)


@pytest.mark.parametrize("kind,seed", CASES)
def test_kkt_conditions_hold(kind, seed):
    with jax.enable_x64(True):
        q_mat, q_vec = _problem(kind, seed)
        x, kkt, steps = _solvers.active_set_batch(
            jnp.asarray(q_mat)[None], jnp.asarray(q_vec)[None], tol=1e-12
        )
        x = np.asarray(x[0])
        g = q_mat @ x + q_vec
        scale = np.abs(np.diag(q_mat)).max() * np.abs(x).max()
        assert np.all(x >= 0)
        assert np.all(g >= -1e-8 * scale)  # dual feasibility
        assert np.abs(x * g).max() <= 1e-8 * scale * np.abs(x).max()  # complementarity
        assert float(kkt[0]) < 1e-9
        assert int(steps) >= 1  # these problems have active bounds: the branch ran


def test_kkt_residual_detects_non_optimal_points():
    with jax.enable_x64(True):
        q_mat, q_vec = _problem("random", 3)
        ref = _reference(q_mat, q_vec)
        r_opt = float(
            _solvers.kkt_residual(jnp.asarray(q_mat), jnp.asarray(q_vec), ref)
        )
        r_bad = float(
            _solvers.kkt_residual(jnp.asarray(q_mat), jnp.asarray(q_vec), ref + 0.05)
        )
        assert r_opt < 1e-9 < 1e-3 < r_bad


def test_unconstrained_and_svd_baselines():
    with jax.enable_x64(True):
        rng = np.random.default_rng(5)
        q_mat, q_vec = _problem("random", 5)
        x = np.asarray(_solvers.unconstrained(jnp.asarray(q_mat), jnp.asarray(q_vec)))
        np.testing.assert_allclose(x, np.linalg.solve(q_mat, -q_vec), rtol=1e-9)
        # SVD null vector: the right singular vector of N with the smallest singular
        # value, scaled to last entry 1.
        x_true = rng.uniform(0.1, 1.0, M)
        rows = rng.standard_normal((30, M + 1))
        rows[:, -1] = -rows[:, :M] @ x_true  # every row ⟂ [x_true; 1]
        rows += 1e-6 * rng.standard_normal(rows.shape)
        got = np.asarray(_solvers.svd_nullvector(jnp.asarray(rows.T @ rows)))
        _, _, vt = np.linalg.svd(rows)
        ref = vt[-1, :M] / vt[-1, M]
        np.testing.assert_allclose(got, ref, rtol=1e-6)
        np.testing.assert_allclose(got, x_true, rtol=1e-4)


@pytest.mark.parametrize("kind,seed", [("random", 0), ("ill", 1), ("banded", 0)])
def test_box_qp_gradient_matches_finite_differences(kind, seed):
    with jax.enable_x64(True):
        q_mat, q_vec = _problem(kind, seed)
        rng = np.random.default_rng(seed + 10)
        w = jnp.asarray(rng.standard_normal(M))
        dq = jnp.asarray(rng.standard_normal((M, M)))
        dq = 0.5 * (dq + dq.T) * 1e-2 * np.abs(q_mat).max()
        dv = jnp.asarray(rng.standard_normal(M)) * 1e-2 * np.abs(q_vec).max()

        def f(s):  # a scalar path through (Q, q) space
            return w @ box_qp(jnp.asarray(q_mat) + s * dq, jnp.asarray(q_vec) + s * dv)

        grad = jax.grad(f)(0.0)
        h = 1e-6
        fd = (f(h) - f(-h)) / (2 * h)
        np.testing.assert_allclose(float(grad), float(fd), rtol=1e-5, atol=1e-9)


def test_solvers_vmap_equals_loop_and_float32_close_to_float64():
    probs = [_problem("random", s) for s in range(4)]
    with jax.enable_x64(True):
        refs = np.stack([_reference(a, b) for a, b in probs])
        q64 = jnp.asarray(np.stack([a for a, _ in probs]))
        v64 = jnp.asarray(np.stack([b for _, b in probs]))
        batch, _, _ = _solvers.active_set_batch(q64, v64, tol=1e-12)
        loop = np.stack(
            [
                _solvers.active_set_batch(q64[i : i + 1], v64[i : i + 1], tol=1e-12)[0][
                    0
                ]
                for i in range(4)
            ]
        )
        np.testing.assert_allclose(np.asarray(batch), loop, rtol=1e-10, atol=1e-12)
    q32 = jnp.asarray(np.stack([a for a, _ in probs]), jnp.float32)
    v32 = jnp.asarray(np.stack([b for _, b in probs]), jnp.float32)
    x32, _, _ = _solvers.active_set_batch(q32, v32, tol=1e-5)
    assert x32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(x32), refs, atol=1e-3 * np.abs(refs).max())


def test_box_qp_survives_float32_rounding_indefinite_q():
    # A Gram whose smallest eigenvalues lie below float32's rounding level (cond ~1e12,
    # like a design-run pixel with few events and weak priors): the plain float32
    # Cholesky fails (NaN); the differentiable solver retries with a shift and gives a
    # finite, non-negative answer with finite gradients, near the float64 solution in
    # the well-determined directions.
    rng = np.random.default_rng(3)
    u, _ = np.linalg.qr(rng.standard_normal((M, M)))
    evals = np.logspace(-8, 4, M)
    evals[0] = 1e-8
    q64 = u @ np.diag(evals) @ u.T
    q64 = 0.5 * (q64 + q64.T)
    x_true = np.abs(rng.standard_normal(M))
    v64 = -q64 @ x_true
    q32, v32 = jnp.asarray(q64, jnp.float32), jnp.asarray(v64, jnp.float32)
    # Find a rounding of Q that makes plain float32 Cholesky fail (so the test
    # exercises the retry), by nudging the smallest eigenvalue negative in float32.
    q32 = q32 - 1e-3 * jnp.asarray(np.outer(u[:, 0], u[:, 0]), jnp.float32)
    plain = jax.scipy.linalg.cho_factor(q32, lower=True)[0]
    assert not np.all(np.isfinite(np.asarray(plain)))
    x = np.asarray(box_qp(q32, v32))
    assert np.all(np.isfinite(x)) and np.all(x >= 0)
    # The stiff directions (eigenvalue ≥ 1) are recovered.
    stiff = u[:, evals >= 1.0]
    np.testing.assert_allclose(stiff.T @ x, stiff.T @ x_true, rtol=0, atol=2e-2)
    grads = jax.grad(lambda a, b: jnp.sum(box_qp(a, b) ** 2), argnums=(0, 1))(q32, v32)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
    # The batched hot path does not retry; its non-finite pixels are the pipeline's to
    # replace and flag (test_reconstruct covers that).
    assert np.all(np.isfinite(np.asarray(_solvers.unconstrained(q32, v32, robust=True))))
