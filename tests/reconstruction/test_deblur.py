"""Undoing the optics' blur (`deblur_cube`) and its use by `reconstruct`."""

import jax
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import evhsi_jax as ev
from evhsi_jax.reconstruction import deblur_cube


def _patches(h=24, w=32, m=3, seed=0):
    rng = np.random.default_rng(seed)
    labels = (np.arange(h)[:, None] // 6) * 8 + np.arange(w)[None, :] // 8
    pal = rng.uniform(0.05, 0.95, (labels.max() + 1, m))
    return pal[labels].astype(np.float64)


@pytest.mark.parametrize("sigma", [0.5, 1.0])
def test_inverts_the_simulators_blur_away_from_the_border(sigma):
    sharp = _patches()
    blurred = gaussian_filter(sharp, (sigma, sigma, 0), mode="nearest")
    out = deblur_cube(blurred, sigma, reg=1e-6)
    inner = (slice(5, -5), slice(5, -5))
    err_before = np.abs(blurred - sharp)[inner].max()
    err_after = np.abs(out - sharp)[inner].max()
    assert err_before > 0.1  # the blur is visible at the patch edges
    assert err_after < 0.05 * err_before  # (σ 0.5: ~1e-4; σ 1: 0.04 of it at λ 1e-6)


@pytest.mark.parametrize("shape", [(13, 17, 2), (12, 16, 3)])
def test_real_transforms_equal_the_full_complex_filter(shape):
    """The half-spectrum (rfft) filter is the Wiener filter of the module docstring
    applied with full complex FFTs, for odd and even grid sizes."""
    from evhsi_jax._reconstruct._deblur import _transfer, gaussian_kernel_1d

    cube = np.random.default_rng(1).uniform(0, 1, shape)
    sigma, reg = 0.8, 0.2
    k = gaussian_kernel_1d(sigma)
    pad = max(8, 3 * (k.size // 2))
    big = np.pad(cube, ((pad, pad), (pad, pad), (0, 0)), "edge")
    tf = _transfer(k, big.shape[0])[:, None] * _transfer(k, big.shape[1])[None, :]
    gain = (tf * (1 + reg) / (tf * tf + reg))[..., None]
    ref = np.fft.ifft2(np.fft.fft2(big, axes=(0, 1)) * gain, axes=(0, 1)).real
    ref = ref[pad:-pad, pad:-pad]
    np.testing.assert_allclose(deblur_cube(cube, sigma, reg), ref, atol=1e-6)


def test_keeps_uniform_areas_and_sharp_input():
    flat = np.full((10, 12, 4), 0.4)
    np.testing.assert_allclose(deblur_cube(flat, 0.7), flat, atol=1e-6)
    cube = _patches()
    assert deblur_cube(cube, 0.0) is cube
    with pytest.raises(ValueError, match="regularisation"):
        deblur_cube(cube, 0.5, reg=0.0)


def test_noise_gain_is_bounded_by_the_regularisation():
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 0.01, (64, 64, 1))
    reg = 0.05
    out = deblur_cube(noise, 0.5, reg=reg)
    bound = (1 + reg) / (2 * np.sqrt(reg))
    assert 1.0 < out.std() / noise.std() < bound


def test_reconstruct_deblurs_by_the_rigs_psf():
    scene = ev.load_scene("colorchecker", (12, 18))
    rig = ev.Rig(psf_sigma_px=0.5, threshold_sigma=0.0)  # exact global thresholds
    events = ev.simulate(scene, rig, sweeps=1, key=jax.random.key(0))
    plain = ev.reconstruct(events, rig, deblur=False)
    sharp = ev.reconstruct(events, rig)  # on by default when the rig has a PSF
    top = ev.reconstruction.ProblemConfig().max_reflectance
    np.testing.assert_array_equal(sharp, np.clip(deblur_cube(plain, 0.5), 0.0, top))
    assert not np.array_equal(sharp, plain)
    ideal = ev.Rig(threshold_sigma=0.0)  # no PSF: nothing to undo
    np.testing.assert_array_equal(
        ev.reconstruct(events, ideal), ev.reconstruct(events, ideal, deblur=False)
    )
