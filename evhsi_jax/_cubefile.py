"""Cube files: `.npz` with `cube` (H, W, M) float32 reflectance and `wavelengths_nm` (M,).

Optional extra keys ride along (a truth file adds `labels`, `names` and the simulated
per-pixel `threshold_on`/`threshold_off` maps).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._events import atomic_write

__all__ = ["save_cube", "load_cube"]


def save_cube(path, cube, wavelengths_nm, **extra) -> None:
    """Write a cube file atomically (whole file or nothing).

    **Arguments:**

    - `cube`: reflectance, shape `(H, W, M)`; stored as float32.
    - `wavelengths_nm`: channel centres, shape `(M,)`.
    - `extra`: further arrays to store (e.g. `labels`).
    """
    cube = np.asarray(cube, dtype=np.float32)
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if cube.ndim != 3 or cube.shape[-1] != wl.size:
        raise ValueError(f"cube {cube.shape} does not match {wl.size} wavelengths")
    arrays = dict(
        cube=cube, wavelengths_nm=wl, **{k: np.asarray(v) for k, v in extra.items()}
    )
    atomic_write(path, lambda f: np.savez(f, **arrays))


def load_cube(path) -> dict:
    """Read a cube file; returns a dict with at least `cube` and `wavelengths_nm`."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cube file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: np.asarray(data[k]) for k in data.files}
    except Exception as err:
        raise ValueError(f"{path} is not a readable .npz file ({err})") from None
    missing = {"cube", "wavelengths_nm"} - set(out)
    if missing:
        raise ValueError(f"{path} is not a cube file: lacks {sorted(missing)}")
    cube, wl = out["cube"], out["wavelengths_nm"]
    if cube.ndim != 3 or wl.ndim != 1 or cube.shape[-1] != wl.size:
        raise ValueError(
            f"{path}: cube {cube.shape} does not match wavelengths_nm {wl.shape}"
        )
    if not np.issubdtype(cube.dtype, np.floating):
        raise ValueError(f"{path}: cube must hold floats, got {cube.dtype}")
    return out
