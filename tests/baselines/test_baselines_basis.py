"""Basis baseline: training set hygiene, SVD basis, least-squares projection."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._baselines import (
    basis_coefficients,
    basis_project,
    learn_basis,
    reflectance_basis,
    training_reflectances,
)


@pytest.fixture(scope="module")
def grid():
    return ev.Rig().grid


@pytest.fixture(scope="module")
def basis(grid):
    return reflectance_basis(grid, 8)


def test_training_set_is_disjoint_from_the_colorchecker(grid):
    import colour

    names, spectra = training_reflectances(grid)
    assert spectra.shape == (len(names), grid.channels)
    # Three test-colour samples resemble ColorChecker patches and are dropped too.
    tcs = [n for n in names if n.startswith(("CIE", "CQS"))]
    assert len(tcs) == 41 and "CIE 1995 TCS10" not in tcs
    assert len(names) == 210
    assert spectra.min() >= 0 and spectra.max() <= 1
    wl = np.arange(380.0, 781.0, 5.0)
    # Every ColorChecker patch (N Ohta) is farther than the tolerance from all
    # training spectra, compared on the channel grid.
    cc = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    cc_chan = np.stack(
        [
            ev.forward.band_integrate(
                wl, np.interp(wl, sd.wavelengths, sd.values), grid.edges_nm
            )
            for sd in cc.values()
        ]
    )
    dist = np.abs(spectra[:, None, :] - cc_chan[None]).max(-1)
    assert dist.min() >= 0.05
    # Without the filter the RAW2ACES set does contain ColorChecker look-alikes.
    _, all_spectra = training_reflectances(grid, colorchecker_tol=0.0)
    assert len(all_spectra) > len(spectra)


def test_basis_is_orthonormal_and_matches_numpy_svd(grid, basis):
    v = basis.vectors
    np.testing.assert_allclose(v.T @ v, np.eye(8), atol=1e-5)
    _, spectra = training_reflectances(grid)
    _, s, vt = np.linalg.svd(spectra.astype(np.float64), full_matrices=False)
    np.testing.assert_allclose(basis.singular_values, s[:8], rtol=1e-4)
    # Same subspace as the float64 reference (signs may differ).
    np.testing.assert_allclose(np.abs(np.sum(v * vt[:8].T, 0)), 1.0, atol=1e-4)
    assert np.all(v[:, 0] > 0)  # the leading vector is all-positive
    assert 0.99 < basis.energy <= 1.0
    assert basis.training_size == len(spectra)


def test_basis_operator_adjoint_float64(basis):
    # Forward c ↦ B c and its adjoint x ↦ Bᵀx (= the LS coefficients, B orthonormal).
    with jax.enable_x64(True):
        b = jnp.asarray(basis.vectors, jnp.float64)
        c = jr.normal(jr.key(0), (5, 8), jnp.float64)
        x = jr.normal(jr.key(1), (5, 72), jnp.float64)
        lhs = jnp.vdot(c @ b.T, x)
        rhs = jnp.vdot(c, basis_coefficients(x, basis))
        np.testing.assert_allclose(float(lhs), float(rhs), rtol=1e-5)


def test_spectrum_in_the_span_is_recovered_exactly(basis):
    rng = np.random.default_rng(0)
    coef = rng.normal(size=(3, 4, 8)).astype(np.float32)
    cube = jnp.asarray(coef @ basis.vectors.T)
    out = basis_project(cube, basis)
    np.testing.assert_allclose(np.asarray(out), np.asarray(cube), atol=1e-5)
    np.testing.assert_allclose(
        np.asarray(basis_coefficients(cube, basis)), coef, atol=1e-5
    )


def test_projection_residual_is_orthogonal_and_narrow_bands_are_lost(grid, basis):
    scene = ev.load_scene("rainbow", (3, 16))
    truth = jnp.asarray(scene.truth_cube(grid))
    proj = basis_project(truth, basis)
    resid = truth - proj
    np.testing.assert_allclose(
        np.asarray(resid @ jnp.asarray(basis.vectors)), 0.0, atol=1e-5
    )
    # Idempotent.
    np.testing.assert_allclose(
        np.asarray(basis_project(proj, basis)), np.asarray(proj), atol=1e-5
    )
    # Eight smooth vectors cannot hold a 10 nm peak.
    assert ev.metrics.sam_deg(np.asarray(proj), np.asarray(truth)) > 10.0


def test_learn_basis_recovers_a_low_rank_training_set():
    rng = np.random.default_rng(2)
    true = np.linalg.qr(rng.normal(size=(20, 3)))[0]
    spectra = rng.normal(size=(50, 3)) @ true.T
    b = learn_basis(spectra.astype(np.float32), np.arange(20.0), 3, name="toy")
    assert b.energy == pytest.approx(1.0, abs=1e-5)
    # The learned vectors span the same subspace.
    np.testing.assert_allclose(
        np.linalg.svd(true.T @ b.vectors, compute_uv=False), 1.0, atol=1e-5
    )
    with pytest.raises(ValueError, match="basis size"):
        learn_basis(spectra, np.arange(20.0), 21)
