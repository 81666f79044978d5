"""Scenes: reflectance images as a palette of spectra and a label image.

Most test scenes are a few materials laid out in patches, so a :class:`Scene` stores each
distinct spectrum once (`palette`, shape `(K, L)` on `wavelengths_nm`) and a label image
`(H, W)` that indexes it; an arbitrary cube is the case K = H·W. The simulator then
computes one intensity trace per spectrum and column instead of one per pixel.

Built-in scenes (any size `HxW`):

- `colorchecker`: the 24 patches of the X-Rite ColorChecker (spectra measured by N. Ohta,
  shipped with colour-science), 4 × 6 layout.
- `gray-chart`: its six neutral patches (white 9.5 … black 2) as six horizontal stripes,
  so that every column sees every gray level (what calibration needs).
- `rainbow`: per column a narrow band (10 nm FWHM peak), a sharp step and a 10 nm notch,
  centred from 420 to 740 nm across the width — structure a few smooth basis spectra
  cannot represent.
- `metamers`: four ColorChecker spectra (top row) and metamers of them (bottom row): the
  same CIE 1931 XYZ under D65, hence the same sRGB, but different spectra.
- `tcs`: 44 test colour samples (CIE 13.3-1995 TCS01–14, CIE 2024 TCS, NIST CQS 9.0
  VS1–15), 4 × 11 layout — the *training* set used to choose the reconstruction's
  weights and for design studies, disjoint from the ColorChecker used for evaluation.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import numpy as np

from .._base import (
    SpectralGrid,
    atomic_write,
    band_integrate,
    read_npz,
    reference_spectra,
)

__all__ = ["Scene", "load_scene", "BUILTIN_SCENES", "parse_size"]

BUILTIN_SCENES = ("colorchecker", "gray-chart", "rainbow", "metamers", "tcs")
DEFAULT_SIZES = {
    "colorchecker": (96, 144),
    "gray-chart": (48, 64),
    "rainbow": (48, 96),
    "metamers": (48, 96),
    "tcs": (32, 88),
}


def _unique_rows(a: np.ndarray):
    """`np.unique(a, axis=0, return_inverse=True)` for a tall matrix with few distinct
    rows, faster: rows are grouped by a random projection (equal rows project equally),
    the groups' representatives sorted as `np.unique` sorts rows, and the grouping
    checked against the rows themselves (a collision falls back to `np.unique`). On a
    48×1280 chart's blur weights 2 ms instead of 85 ms."""
    proj = a @ np.random.default_rng(0).standard_normal(a.shape[1])
    _, first, inv = np.unique(proj, return_index=True, return_inverse=True)
    uniq, order = np.unique(a[first], axis=0, return_inverse=True)
    inv = order.reshape(-1)[inv.reshape(-1)]
    if uniq.shape[0] != first.size or not np.array_equal(uniq[inv], a):
        uniq, inv = np.unique(a, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1)


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A static reflectance scene.

    **Arguments:**

    - `palette`: distinct reflectance spectra, shape `(K, L)`, values in [0, 1].
    - `wavelengths_nm`: their sample wavelengths, shape `(L,)`, increasing.
    - `labels`: index into `palette` per pixel, shape `(H, W)`.
    - `names`: optional name per palette entry (e.g. ColorChecker patch names).
    """

    palette: np.ndarray
    wavelengths_nm: np.ndarray
    labels: np.ndarray
    names: tuple | list = ()

    def __post_init__(self):
        pal = np.asarray(self.palette, dtype=np.float64)
        wl = np.asarray(self.wavelengths_nm, dtype=np.float64)
        lab = np.asarray(self.labels)
        if pal.ndim != 2 or wl.ndim != 1 or pal.shape[1] != wl.size:
            raise ValueError(
                f"scene palette {pal.shape} does not match wavelengths {wl.shape}"
            )
        if not np.all(np.isfinite(pal)):
            raise ValueError("scene reflectance contains NaN or Inf")
        if pal.size and (pal.min() < 0 or pal.max() > 1 + 1e-6):
            raise ValueError(
                f"scene reflectance must lie in [0, 1], got [{pal.min():.3g}, "
                f"{pal.max():.3g}]"
            )
        if wl.size < 2 or np.any(np.diff(wl) <= 0):
            raise ValueError("scene wavelengths_nm must be increasing (>= 2 samples)")
        if lab.ndim != 2 or lab.size == 0 or not np.issubdtype(lab.dtype, np.integer):
            raise ValueError("scene labels must be a non-empty 2-D integer image")
        if lab.min() < 0 or lab.max() >= pal.shape[0]:
            raise ValueError("scene labels index outside the palette")
        object.__setattr__(self, "palette", np.clip(pal, 0.0, 1.0))
        object.__setattr__(self, "wavelengths_nm", wl)
        object.__setattr__(self, "labels", lab.astype(np.int32))
        object.__setattr__(self, "names", tuple(self.names))

    @property
    def height(self) -> int:
        return int(self.labels.shape[0])

    @property
    def width(self) -> int:
        return int(self.labels.shape[1])

    def reflectance(self) -> np.ndarray:
        """The full cube on the scene's own wavelengths, shape `(H, W, L)`."""
        return self.palette[self.labels]

    def palette_on(self, edges_nm) -> np.ndarray:
        """Palette band-integrated into the bins `edges_nm`, shape `(K, B)`."""
        return band_integrate(self.wavelengths_nm, self.palette, edges_nm, name="scene")

    def blurred(self, sigma_px: float) -> Scene:
        """The scene seen through a Gaussian point-spread function of σ pixels (edges
        continued; applied to reflectance, which is exact where neighbouring columns
        see the same band — the blur is much narrower than the band's width on the
        sensor for the default rig, whose band spans hundreds of columns).

        With few palette entries the labels are blurred as weights and identical
        mixtures share one entry (a chart of patches stays a small palette); else
        every pixel gets its own entry."""
        from scipy.ndimage import gaussian_filter

        if sigma_px <= 0:
            return self
        h, w = self.labels.shape
        k = self.palette.shape[0]
        if k <= 256:
            onehot = (self.labels[..., None] == np.arange(k)).astype(np.float64)
            wts = gaussian_filter(onehot, (sigma_px, sigma_px, 0), mode="nearest")
            uniq, inv = _unique_rows(np.round(wts.reshape(h * w, k), 12))
            return Scene(
                np.clip(uniq @ self.palette, 0.0, 1.0),
                self.wavelengths_nm,
                inv.reshape(h, w),
            )
        cube = gaussian_filter(
            self.palette[self.labels], (sigma_px, sigma_px, 0), mode="nearest"
        )
        return Scene(
            np.clip(cube.reshape(h * w, -1), 0.0, 1.0),
            self.wavelengths_nm,
            np.arange(h * w).reshape(h, w),
        )

    def truth_cube(self, grid: SpectralGrid) -> np.ndarray:
        """Reflectance averaged over each channel, shape `(H, W, M)`, float32."""
        return self.palette_on(grid.edges_nm).astype(np.float32)[self.labels]

    @classmethod
    def from_cube(cls, reflectance, wavelengths_nm) -> Scene:
        """A scene from a full cube `(H, W, L)` (identical spectra share an entry)."""
        cube = np.asarray(reflectance, dtype=np.float64)
        if cube.ndim != 3:
            raise ValueError(f"reflectance must be (H, W, L), got shape {cube.shape}")
        h, w, n = cube.shape
        pal, inv = np.unique(cube.reshape(-1, n), axis=0, return_inverse=True)
        return cls(pal, wavelengths_nm, inv.reshape(h, w))

    def save_npz(self, path) -> None:
        """Write the contract scene format (`reflectance`, `wavelengths_nm`)."""
        arrays = dict(
            reflectance=self.reflectance().astype(np.float32),
            wavelengths_nm=self.wavelengths_nm,
        )
        atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def parse_size(text: str | None) -> tuple[int, int] | None:
    """Parse `HxW` (e.g. `720x1280`) into `(H, W)`."""
    if text is None:
        return None
    parts = str(text).lower().split("x")
    try:
        h, w = (int(p) for p in parts)
    except ValueError:
        raise ValueError(
            f"size must look like HxW (e.g. 96x144), got {text!r}"
        ) from None
    if h < 1 or w < 1 or h > 8192 or w > 8192:
        raise ValueError(f"size must be between 1x1 and 8192x8192, got {text!r}")
    return h, w


def _grid_labels(h, w, rows, cols):
    yy = (np.arange(h) * rows) // h
    xx = (np.arange(w) * cols) // w
    return yy[:, None] * cols + xx[None, :]


@functools.lru_cache(maxsize=1)
def _colorchecker():
    ref = reference_spectra()  # colour-science's "ColorChecker N Ohta"
    names = [str(n) for n in ref["colorchecker_names"]]
    return names, ref["colorchecker_wavelengths_nm"], ref["colorchecker_values"]


def colorchecker(size=None) -> Scene:
    h, w = size or DEFAULT_SIZES["colorchecker"]
    names, wl, pal = _colorchecker()
    return Scene(pal, wl, _grid_labels(h, w, 4, 6), names)


def gray_chart(size=None) -> Scene:
    h, w = size or DEFAULT_SIZES["gray-chart"]
    names, wl, pal = _colorchecker()
    return Scene(pal[18:24], wl, _grid_labels(h, w, 6, 1), names[18:24])


def rainbow(size=None) -> Scene:
    h, w = size or DEFAULT_SIZES["rainbow"]
    wl = np.arange(380.0, 780.5, 0.5)
    centre = 420.0 + 320.0 * (np.arange(w) / max(w - 1, 1))
    sig = 10.0 / (2 * np.sqrt(2 * np.log(2)))
    d = wl[None, :] - centre[:, None]
    peak = 0.03 + 0.9 * np.exp(-0.5 * (d / sig) ** 2)
    step = np.where(d >= 0, 0.85, 0.05)
    notch = 0.85 - 0.8 * np.exp(-0.5 * (d / sig) ** 2)
    pal = np.concatenate([peak, step, notch])
    band = (np.arange(h) * 3) // h
    labels = band[:, None] * w + np.arange(w)[None, :]
    names = [f"{kind} {c:.0f} nm" for kind in ("peak", "step", "notch") for c in centre]
    return Scene(pal, wl, labels, names)


def metamer_pair(base: np.ndarray, wl: np.ndarray, period_nm: float, phase: float):
    """A metamer of `base` under D65 / CIE 1931 2°: same XYZ, different spectrum.

    Adds a "metameric black" — a sinusoid of the given period restricted to 400–760 nm
    with its projection on the three weighted colour-matching functions removed — scaled
    as far as the [0.02, 0.98] reflectance range allows (at most ±0.25).
    """
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    xyz_bar = np.stack(
        [np.interp(wl, cmfs.wavelengths, cmfs.values[:, i]) for i in range(3)]
    )
    d65 = colour.SDS_ILLUMINANTS["D65"]
    s = np.interp(wl, d65.wavelengths, d65.values)
    inside = (wl >= 400) & (wl <= 760)
    phi = (xyz_bar * s)[:, inside]  # 3 × L_in
    v = np.sin(2 * np.pi * (wl[inside] - 400.0) / period_nm + phase)
    v = v - phi.T @ np.linalg.solve(phi @ phi.T, phi @ v)
    v /= np.abs(v).max()
    b = base[inside]
    room_up = np.where(v > 0, (0.98 - b) / np.where(v > 0, v, 1), np.inf)
    room_dn = np.where(v < 0, (b - 0.02) / np.where(v < 0, -v, 1), np.inf)
    amp = min(0.25, room_up.min(), room_dn.min())
    out = base.copy()
    out[inside] = b + amp * v
    return out


def metamers(size=None) -> Scene:
    h, w = size or DEFAULT_SIZES["metamers"]
    names, wl, pal = _colorchecker()
    picks = ["foliage", "yellow green", "orange yellow", "neutral 8 (.23 D)"]
    base = [pal[names.index(k)] for k in picks]
    twins = [
        metamer_pair(b, wl, period_nm=p, phase=ph)
        for b, p, ph in zip(base, (120.0, 90.0, 150.0, 100.0), (0.3, 1.1, 2.0, 0.7))
    ]
    palette = np.stack(base + twins)
    labels = _grid_labels(h, w, 2, 4)
    return Scene(palette, wl, labels, picks + [f"{k} (metamer)" for k in picks])


@functools.lru_cache(maxsize=1)
def _tcs():
    from colour.quality.datasets.tcs import SDS_TCS
    from colour.quality.datasets.vs import SDS_VS

    wl = np.arange(380.0, 781.0, 5.0)
    names, rows = [], []
    for group, sds in (
        ("CIE 1995", SDS_TCS["CIE 1995"]),
        ("CIE 2024", SDS_TCS["CIE 2024"]),
        ("CQS 9.0", SDS_VS["NIST CQS 9.0"]),
    ):
        for key, sd in sds.items():
            names.append(f"{group} {key}")
            rows.append(np.interp(wl, sd.wavelengths, sd.values))
    return names, wl, np.clip(np.stack(rows), 0.0, 1.0)


def tcs(size=None) -> Scene:
    h, w = size or DEFAULT_SIZES["tcs"]
    names, wl, pal = _tcs()
    return Scene(pal, wl, _grid_labels(h, w, 4, 11), names)


_BUILDERS = {
    "colorchecker": colorchecker,
    "gray-chart": gray_chart,
    "rainbow": rainbow,
    "metamers": metamers,
    "tcs": tcs,
}


def load_scene(name_or_path: str | os.PathLike, size=None) -> Scene:
    """A built-in scene by name, or a scene `.npz` (`reflectance`, `wavelengths_nm`).

    **Arguments:**

    - `name_or_path`: one of `BUILTIN_SCENES`, or a path to a scene file.
    - `size`: `(H, W)` for built-in scenes (a file's size is its own; passing a
      different size for a file is an error).
    """
    key = str(name_or_path)
    if key in _BUILDERS:
        return _BUILDERS[key](size)
    path = Path(key)
    if path.suffix != ".npz":
        raise ValueError(
            f"unknown scene {key!r}: use one of {', '.join(BUILTIN_SCENES)} or a "
            ".npz scene file"
        )
    keys = ("reflectance", "wavelengths_nm")
    arrays = read_npz(path, "scene file")
    missing = set(keys) - set(arrays)
    if missing:
        raise ValueError(f"scene file {path} lacks keys {sorted(missing)}")
    refl, wl = arrays["reflectance"], arrays["wavelengths_nm"]
    if refl.ndim != 3:
        raise ValueError(f"{path}: reflectance must be (H, W, L), got {refl.shape}")
    if size is not None and tuple(size) != refl.shape[:2]:
        raise ValueError(
            f"{path} is {refl.shape[0]}x{refl.shape[1]}; --size cannot resize a file"
        )
    try:
        return Scene.from_cube(refl, wl)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
