"""Rendering reflectance cubes to sRGB (CIE 1931 2°, D65, colour-science) and PNG files."""

from __future__ import annotations

import functools
import io

import numpy as np

from .._base import atomic_write, band_integrate

__all__ = ["cube_to_srgb", "write_png", "write_comparison_png"]


@functools.lru_cache(maxsize=8)
def _xyz_weights(wavelengths_key: tuple) -> np.ndarray:
    """Per-channel weights (M, 3): CMFs × D65 integrated over each channel."""
    import colour

    centres = np.asarray(wavelengths_key)
    half = 0.5 * np.diff(centres).mean() if centres.size > 1 else 2.5
    edges = np.concatenate([centres - half, centres[-1:] + half])
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    wl = np.asarray(cmfs.wavelengths, np.float64)
    s = np.interp(wl, d65.wavelengths, d65.values)
    weighted = np.asarray(cmfs.values, np.float64).T * s  # (3, L)
    per_channel = band_integrate(wl, weighted, edges).T * np.diff(edges)[:, None]
    # Normalise so a perfect white reflector over the *full* visible range has Y = 1.
    y_white = np.sum(0.5 * (weighted[1, 1:] + weighted[1, :-1]) * np.diff(wl))
    return per_channel / y_white


def cube_to_srgb(cube, wavelengths_nm) -> np.ndarray:
    """sRGB rendering of a reflectance cube seen under D65 by the CIE 1931 observer.

    Channels outside the cube's range contribute nothing (a 400–760 nm cube of a white
    reflector renders at Y ≈ 0.998). Values are clipped to [0, 1] after the sRGB
    transfer function.

    **Arguments:**

    - `cube`: reflectance, shape `(H, W, M)`.
    - `wavelengths_nm`: channel centres, shape `(M,)`, evenly spaced.

    **Returns:** sRGB in [0, 1], shape `(H, W, 3)`, float32.

    A float32 cube is weighed in float32 (one matrix product over the cube as it is:
    converting a 1280×720×72 cube to float64 and replacing its non-finite values
    first had cost ~1.6 s per sweep of `reconstruct_sweeps`, which stores each
    sweep's rendering); only pixels with a non-finite channel are weighed again in
    float64 with NaN as 0 and ±inf as the largest finite numbers.
    """
    import colour

    cube = np.asarray(cube)
    if cube.dtype not in (np.float32, np.float64):
        cube = cube.astype(np.float64)
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if cube.ndim != 3 or cube.shape[-1] != wl.size:
        raise ValueError(
            f"cube shape {cube.shape} does not match {wl.size} wavelengths"
        )
    weights = _xyz_weights(tuple(np.round(wl, 6)))
    flat = cube.reshape(-1, wl.size)
    # A non-finite channel makes its pixel's product non-finite (weighed again below);
    # whether the BLAS kernel also raises the invalid flag depends on the CPU (AVX2
    # OpenBLAS kernels do, AVX-512 ones did not), so the flag is not a signal here.
    with np.errstate(invalid="ignore", over="ignore"):
        xyz = (flat @ weights.astype(cube.dtype)).astype(np.float64)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        xyz[bad] = np.nan_to_num(flat[bad].astype(np.float64)) @ weights
    xyz = xyz.reshape(*cube.shape[:-1], 3)
    rgb = colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=True)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def _png_bytes(rgb: np.ndarray) -> bytes:
    import matplotlib.image

    buf = io.BytesIO()
    matplotlib.image.imsave(buf, np.asarray(rgb), format="png")
    return buf.getvalue()


def write_png(path, rgb) -> None:
    """Write an `(H, W, 3)` float image in [0, 1] as PNG (atomically)."""
    data = _png_bytes(rgb)
    atomic_write(path, lambda f: f.write(data))


def write_comparison_png(path, panels: dict, *, scale: int = 4) -> None:
    """Side-by-side sRGB panels with titles, e.g. `{"truth": rgb1, "ours": rgb2}`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(panels)
    h, w = next(iter(panels.values())).shape[:2]
    fig, axes = plt.subplots(
        1,
        n,
        figsize=(n * max(2.5, w * scale / 100), 0.5 + max(2.0, h * scale / 100)),
        squeeze=False,
    )
    for ax, (title, img) in zip(axes[0], panels.items()):
        ax.imshow(np.asarray(img), interpolation="nearest")
        ax.set_title(title)
        ax.axis("off")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    data = buf.getvalue()
    atomic_write(path, lambda f: f.write(data))
