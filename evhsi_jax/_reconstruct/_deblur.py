"""Undo the optics' blur on a reconstructed cube (Wiener deconvolution per channel).

A pixel's events see the scene through the lens's point-spread function: what the
per-pixel reconstruction returns is the reflectance blurred by it (exactly so where
neighbouring columns see the same band, which holds for blurs of a few pixels: the band
spans hundreds of columns). The calibration measures the blur as a Gaussian of
`psf_sigma_px` pixels (:func:`evhsi_jax.calibration.threshold_maps_from_chart`, the
same sampled kernel as :meth:`evhsi_jax.Scene.blurred`), and this module inverts it.

Filter: $X = Y H (1 + λ) / (H^2 + λ)$ per channel, with $H$ the kernel's (real)
transfer function on an edge-padded FFT grid: a Wiener filter scaled to pass a uniform
area unchanged. λ trades sharpness against noise: the reconstruction's per-pixel error
is roughly white, and $(1 + λ) / (2\\sqrt{λ})$ bounds its amplification at any
frequency. A NumPy/SciPy post-process of the cube (no solve is changed); not
differentiable. The transforms are real-to-complex (`scipy.fft.rfft2`: the cube and
the filter are real, so half the spectrum suffices) on every core, in float32: on a
360×640 `realistic` capture NumPy's complex transforms on one core had been a quarter
of the whole reconstruction (4.0 of 16.2 s). Where the reconstruction left its cube
on a GPU, the same filter runs there (:func:`deblur_cube_device`, JAX's FFT), and the
cube comes home deblurred.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft

from .._base import shard

__all__ = ["gaussian_kernel_1d", "deblur_cube", "DEFAULT_WIENER_REG"]

#: λ of the Wiener filter, chosen by the mean PSNR over the TCS and rainbow scenes (not
#: the ColorChecker that the studies evaluate on) at the `realistic` preset:
#: `experiments/deblur.py`.
DEFAULT_WIENER_REG = 0.2


def gaussian_kernel_1d(sigma_px: float) -> np.ndarray:
    """The sampled, normalised Gaussian of σ pixels, radius ⌊4σ + ½⌋ (the kernel of
    `scipy.ndimage.gaussian_filter`, which the simulator's optics use)."""
    r = int(4.0 * sigma_px + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma_px) ** 2)
    return k / k.sum()


def _transfer(kernel: np.ndarray, n: int) -> np.ndarray:
    """Real transfer function (the kernel is symmetric) on an `n`-point FFT grid."""
    r = kernel.size // 2
    f = np.fft.fftfreq(n)
    j = np.arange(-r, r + 1)
    return (kernel[None, :] * np.cos(2 * np.pi * f[:, None] * j[None, :])).sum(1)


def _wiener_plan(sigma_px: float, reg: float, h: int, w: int):
    """(padding, filter): the edge padding of an `h`×`w` image and the Wiener
    filter's gain `(H + 2·pad, (W + 2·pad) // 2 + 1)` float32 on that grid's rfft
    frequencies."""
    if not reg > 0:
        raise ValueError(f"the Wiener regularisation must be > 0, got {reg}")
    k = gaussian_kernel_1d(sigma_px)
    pad = max(8, 3 * (k.size // 2))
    hy = _transfer(k, h + 2 * pad)
    hx = _transfer(k, w + 2 * pad)
    tf = hy[:, None] * hx[None, :]
    gain = tf * (1.0 + reg) / (tf * tf + reg)  # DC gain 1: levels kept
    # (rfft's frequencies: the first half of fft's)
    return pad, gain[:, : (w + 2 * pad) // 2 + 1].astype(np.float32)


def deblur_cube(
    cube: np.ndarray, sigma_px: float, reg: float = DEFAULT_WIENER_REG
) -> np.ndarray:
    """Wiener-deconvolve every channel of `cube` `(H, W, M)` by the Gaussian PSF of
    `sigma_px` pixels; returns a new float32 cube (unclipped). σ ≤ 0 returns the
    cube unchanged."""
    if sigma_px <= 0:
        return cube
    h, w, _ = cube.shape
    pad, gain = _wiener_plan(sigma_px, reg, h, w)
    # In float32, the cube's own precision (SciPy's single-precision transforms):
    # against float64 transforms the answer moves by < 1e-6 on a unit-range cube, in
    # about a third of the time and ~60 % of the memory (experiments/bench_deblur_ab.py).
    big = np.pad(
        cube.astype(np.float32, copy=False), ((pad, pad), (pad, pad), (0, 0)), "edge"
    )
    cores = shard.usable_cores()
    spec = scipy.fft.rfft2(big, axes=(0, 1), workers=cores)
    spec *= gain[:, :, None]
    out = scipy.fft.irfft2(spec, s=big.shape[:2], axes=(0, 1), workers=cores)
    return out[pad : pad + h, pad : pad + w].astype(np.float32)


def deblur_cube_device(cube, sigma_px: float, reg: float = DEFAULT_WIENER_REG,
                       clip_max: float | None = None):  # fmt: skip
    """:func:`deblur_cube` of a JAX cube `(H, W, M)` float32 where it is (a GPU's
    FFT: the cube does not go to the host and back), then clipped to
    [0, `clip_max`] (None: not clipped). The same filter; the transforms' rounding
    differs from SciPy's (float32 both)."""
    if sigma_px <= 0:
        return cube if clip_max is None else jnp.clip(cube, 0.0, clip_max)
    h, w, _ = cube.shape
    pad, gain = _wiener_plan(sigma_px, reg, h, w)
    return _wiener(cube, jnp.asarray(gain), pad, clip_max)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _wiener(cube, gain, pad: int, clip_max):
    h, w, _ = cube.shape
    big = jnp.pad(cube, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    spec = jnp.fft.rfft2(big, axes=(0, 1)) * gain[:, :, None].astype(jnp.complex64)
    out = jnp.fft.irfft2(spec, s=big.shape[:2], axes=(0, 1))[pad : pad + h, pad : pad + w]
    out = out.astype(jnp.float32)
    return out if clip_max is None else jnp.clip(out, 0.0, clip_max)
