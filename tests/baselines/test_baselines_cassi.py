"""CASSI simulator, GAP-TV and DeSCI: operator identities and known-answer recovery."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._baselines import (
    CassiOperator,
    PatchConfig,
    block_match,
    cassi_measure,
    desci,
    gap_tv,
    random_mask,
    tv_denoise,
    wnnm_denoise,
)
from evhsi_jax._baselines._gaptv import _div, _grad


def _reference_forward(mask, cube, shift):
    """Independent NumPy SD-CASSI: loop over channels, shift the coded band."""
    h, w, m = cube.shape
    y = np.zeros((h, w + shift * (m - 1)))
    for k in range(m):
        y[:, shift * k : shift * k + w] += mask * cube[:, :, k]
    return y


@pytest.mark.parametrize("shift", [1, 2])
def test_cassi_forward_matches_numpy_and_adjoint_float64(shift):
    with jax.enable_x64(True):
        mask = random_mask(6, 7, key=jr.key(0)).astype(jnp.float64)
        op = CassiOperator(mask, 5, shift)
        assert op.measurement_shape == (6, 7 + shift * 4)
        x = jr.normal(jr.key(1), op.cube_shape, jnp.float64)
        y = jr.normal(jr.key(2), op.measurement_shape, jnp.float64)
        np.testing.assert_allclose(
            np.asarray(op(x)),
            _reference_forward(np.asarray(mask), np.asarray(x), shift),
        )
        lhs, rhs = jnp.vdot(op(x), y), jnp.vdot(x, op.adjoint(y))
        np.testing.assert_allclose(float(lhs), float(rhs), rtol=1e-12)


def test_normaliser_is_the_diagonal_of_a_at():
    with jax.enable_x64(True):
        op = CassiOperator(random_mask(3, 4, key=jr.key(5)).astype(jnp.float64), 3, 1)
        n = int(np.prod(op.cube_shape))
        a = jax.vmap(lambda e: op(e.reshape(op.cube_shape)).ravel())(jnp.eye(n)).T
        aat = np.asarray(a @ a.T)
        np.testing.assert_allclose(np.diag(aat), np.diag(aat) * 0 + np.diag(aat))
        off = aat - np.diag(np.diag(aat))
        assert np.abs(off).max() == 0.0  # AAᵀ is diagonal for SD-CASSI
        diag = np.diag(aat).reshape(op.measurement_shape)
        expect = np.where(diag > 0, diag, 1.0)
        np.testing.assert_allclose(np.asarray(op.normaliser()), expect)


def test_measurement_noise_and_quantisation():
    op = CassiOperator(random_mask(8, 8, key=jr.key(0)), 4, 1)
    cube = jnp.full(op.cube_shape, 0.5)
    clean = cassi_measure(cube, op)
    q = cassi_measure(cube, op, bits=8)
    assert float(jnp.abs(q - clean).max()) <= 0.5 * float(clean.max()) / 255 + 1e-6
    with pytest.raises(ValueError, match="key"):
        cassi_measure(cube, op, noise_sigma=0.1)


def test_divergence_is_the_negative_adjoint_of_the_gradient():
    with jax.enable_x64(True):
        u = jr.normal(jr.key(0), (5, 6, 2), jnp.float64)
        p = jr.normal(jr.key(1), (2, 5, 6, 2), jnp.float64)
        np.testing.assert_allclose(
            float(jnp.vdot(_grad(u), p)), float(-jnp.vdot(u, _div(p))), rtol=1e-12
        )


def test_tv_denoise_removes_noise_from_a_step():
    clean = jnp.zeros((16, 16, 2)).at[:, 8:].set(1.0)
    noisy = clean + 0.1 * jr.normal(jr.key(0), clean.shape)
    out = tv_denoise(noisy, 0.1, iters=100)
    assert float(jnp.std(out - clean)) < 0.4 * float(jnp.std(noisy - clean))
    flat = jnp.full((8, 8, 1), 0.3)
    np.testing.assert_allclose(np.asarray(tv_denoise(flat, 0.1)), 0.3, atol=1e-6)


def _piecewise_scene(m=8, h=16, w=16):
    wl = np.linspace(0, 1, m)
    specs = np.stack(
        [0.2 + 0.6 * wl, 0.8 - 0.5 * wl, 0.5 + 0.3 * np.sin(6 * wl), np.full(m, 0.3)]
    )
    lab = (np.arange(h)[:, None] >= h // 2) * 2 + (np.arange(w)[None] >= w // 2)
    return jnp.asarray(specs[lab], jnp.float32)


@pytest.fixture(scope="module")
def piecewise():
    cube = _piecewise_scene()
    op = CassiOperator(random_mask(16, 16, key=jr.key(3)), 8, 1)
    return cube, op, cassi_measure(cube, op)


def test_gap_tv_recovers_a_piecewise_constant_scene(piecewise):
    cube, op, y = piecewise
    start = op.adjoint(y / op.normaliser())
    est = gap_tv(y, op, iters=300, tv_weight=0.05, tv_weight_end=0.001)
    e, t = np.asarray(est), np.asarray(cube)
    assert ev.metrics.psnr_db(np.asarray(start), t) < 15  # the problem is not trivial
    assert ev.metrics.psnr_db(e, t) > 25
    assert ev.metrics.sam_deg(e, t) < 2.0
    # Away from the region boundaries the recovery is near-exact.
    err = np.abs(e - t).max(-1)
    assert np.median(err) < 0.005
    # The data are matched.
    rel = float(jnp.linalg.norm(op(est) - y) / jnp.linalg.norm(y))
    assert rel < 1e-2


def test_block_match_finds_exact_repeats():
    rng = np.random.default_rng(0)
    tile = rng.uniform(size=(4, 4, 3)).astype(np.float32)
    img = jnp.asarray(np.tile(tile, (4, 4, 1)))  # period 4 in both directions
    cfg = PatchConfig(patch=4, step=4, window=4, search_step=1, group=4)
    corners = np.asarray(block_match(img, cfg))
    rows, cols = cfg.references(16, 16)
    np.testing.assert_array_equal(corners[:, 0, 0], rows)  # reference first
    np.testing.assert_array_equal(corners[:, 0, 1], cols)
    # All group members are exact copies: offsets are multiples of the period.
    assert np.all((corners - corners[:, :1]) % 4 == 0)


def test_wnnm_leaves_a_low_rank_cube_unchanged_and_denoises():
    cube = _piecewise_scene(m=6)
    cfg = PatchConfig(patch=4, step=2, window=4, search_step=1, group=8)
    corners = block_match(cube, cfg)
    same = wnnm_denoise(cube, 0.01, corners, cfg.patch)
    np.testing.assert_allclose(np.asarray(same), np.asarray(cube), atol=2e-3)
    noisy = cube + 0.05 * jr.normal(jr.key(0), cube.shape)
    den = wnnm_denoise(noisy, 0.05, block_match(noisy, cfg), cfg.patch)
    assert float(jnp.std(den - cube)) < 0.6 * float(jnp.std(noisy - cube))


def test_desci_recovers_a_piecewise_constant_scene(piecewise):
    cube, op, y = piecewise
    start = gap_tv(y, op, iters=300, tv_weight=0.05, tv_weight_end=0.001)
    cfg = PatchConfig(patch=4, step=2, window=4, search_step=1, group=16)
    est = desci(y, op, iters=100, sigma=0.1, sigma_end=0.01, patches=cfg, x0=start)
    e, t = np.asarray(est), np.asarray(cube)
    assert ev.metrics.psnr_db(e, t) > 40
    assert ev.metrics.psnr_db(e, t) > ev.metrics.psnr_db(np.asarray(start), t) + 10
    assert ev.metrics.sam_deg(e, t) < 0.5
