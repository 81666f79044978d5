"""Cube files, by extension, wherever a cube goes in or out.

- `.npz`: `cube` (H, W, M) float32 reflectance and `wavelengths_nm` (M,) (the contract
  format). Optional extra keys ride along (a truth file adds `labels`, `names` and the
  simulated per-pixel `threshold_on`/`threshold_off` maps; `reconstruct` adds
  `events_per_pixel` and `kkt`).
- `.hdr`: ENVI, written through Spectral Python (SPy, the field's reference reader and
  writer of ENVI): `NAME.hdr` + `NAME.img` (float32, band-sequential, little-endian),
  with `wavelength`, `wavelength units = Nanometers`, `band names`, `data ignore value
  = -1` (non-finite values are stored as -1 and read back as NaN; reflectance is never
  negative), `reflectance scale factor = 1` and a `description`. ENVI holds one
  image; the extra arrays go to a sibling `NAME.evhsi.npz` that :func:`load_cube`
  merges back (ENVI tools ignore it). Reading takes any ENVI file SPy reads, so cubes
  from other software load too (`wavelength` in nm or µm).
- `.zarr`: a Zarr store (through xarray) holding one cube as the variable
  `reflectance` (y, x, wavelength) with a `wavelength` coordinate in nm. The per-sweep
  *video* store, with a `time` axis, is written by :mod:`evhsi_jax._video._stream` and is
  read sweep by sweep with :func:`evhsi_jax.video.iter_sweep_cubes`.

All writes are whole or nothing: every file of a cube is written under a temporary
name in the destination folder and renamed into place, the entry file (`.hdr`, the
`.zarr` folder) last.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np

from .._base import atomic_write, one_line, read_npz

__all__ = ["save_cube", "load_cube", "CUBE_SUFFIXES", "ENVI_IGNORE"]

CUBE_SUFFIXES = (".npz", ".hdr", ".zarr")
ENVI_IGNORE = -1.0


def _suffix(path) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in CUBE_SUFFIXES + (".img",):
        raise ValueError(
            f"{path}: unknown cube file extension {suffix!r} (expected "
            f"{', '.join(CUBE_SUFFIXES)})"
        )
    return suffix


def save_cube(path, cube, wavelengths_nm, **extra) -> None:
    """Write a cube file atomically (whole file or nothing), format by extension.

    **Arguments:**

    - `path`: `.npz`, `.hdr` (ENVI, with `.img` beside it) or `.zarr`.
    - `cube`: reflectance, shape `(H, W, M)`; stored as float32.
    - `wavelengths_nm`: channel centres, shape `(M,)`.
    - `extra`: further arrays to store (e.g. `labels`).
    """
    cube = np.asarray(cube, dtype=np.float32)
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if cube.ndim != 3 or cube.shape[-1] != wl.size:
        raise ValueError(f"cube {cube.shape} does not match {wl.size} wavelengths")
    extra = {k: np.asarray(v) for k, v in extra.items()}
    suffix = _suffix(path)
    if suffix == ".npz":
        arrays = dict(cube=cube, wavelengths_nm=wl, **extra)
        atomic_write(path, lambda f: np.savez(f, **arrays))
    elif suffix == ".zarr":
        _save_zarr(Path(path), cube, wl, extra)
    else:
        _save_envi(Path(path).with_suffix(".hdr"), cube, wl, extra)


def load_cube(path) -> dict:
    """Read a cube file by extension; returns a dict with at least `cube` (H, W, M)
    and `wavelengths_nm` (M,), plus any extra arrays the file carries."""
    path = Path(path)
    suffix = _suffix(path)
    if suffix == ".npz":
        out = read_npz(path, "cube file")
    elif suffix == ".zarr":
        out = _load_zarr(path)
    else:
        out = _load_envi(path.with_suffix(".hdr"))
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
    if not np.issubdtype(wl.dtype, np.number) or not np.all(np.isfinite(wl)):
        raise ValueError(f"{path}: wavelengths must be finite numbers")
    return out


# --- ENVI -----------------------------------------------------------------------------
def _extra_path(hdr: Path) -> Path:
    return hdr.with_name(hdr.stem + ".evhsi.npz")


def _save_envi(hdr: Path, cube, wl, extra) -> None:
    import spectral.io.envi as envi

    folder = hdr.parent if str(hdr.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"cannot write {hdr}: folder {folder} does not exist")
    meta = {
        "description": "evhsi_jax reflectance cube",
        "wavelength": [f"{v:.4f}" for v in wl],
        "wavelength units": "Nanometers",
        "band names": [f"{v:.1f} nm" for v in wl],
        "data ignore value": ENVI_IGNORE,
        "reflectance scale factor": 1,
    }
    data = np.where(np.isfinite(cube), cube, np.float32(ENVI_IGNORE))
    tmp = Path(tempfile.mkdtemp(prefix=f".{hdr.name}.", dir=folder))
    try:
        envi.save_image(
            str(tmp / hdr.name),
            data,
            dtype=np.float32,
            interleave="bsq",
            byteorder=0,
            metadata=meta,
            force=True,
            ext=".img",
        )
        if extra:
            np.savez(tmp / _extra_path(hdr).name, **extra)
        elif _extra_path(hdr).exists():  # a stale sibling of an older cube
            _extra_path(hdr).unlink()
        # The image and extras first, the header (the entry point) last.
        for name in (hdr.with_suffix(".img").name, _extra_path(hdr).name, hdr.name):
            if (tmp / name).exists():
                os.replace(tmp / name, folder / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _load_envi(hdr: Path) -> dict:
    import spectral.io.envi as envi

    if not hdr.is_file():
        raise ValueError(f"cube file not found: {hdr} (an ENVI cube is .hdr + .img)")
    try:
        img = envi.open(str(hdr))
        cube = np.asarray(img.load(), dtype=np.float32)
        meta = img.metadata
    except Exception as err:  # SPy raises its own types for bad headers and sizes
        msg = one_line(err, 160)
        raise ValueError(f"{hdr} is not a readable ENVI cube ({msg})") from None
    raw_wl = meta.get("wavelength")
    if raw_wl is None:
        raise ValueError(f"{hdr}: the ENVI header has no 'wavelength' field")
    try:
        wl = np.asarray([float(v) for v in raw_wl], np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{hdr}: 'wavelength' must hold numbers") from None
    units = str(meta.get("wavelength units", "nanometers")).strip().lower()
    if units in ("micrometers", "microns", "um", "µm"):
        wl = wl * 1e3
    elif units not in ("nanometers", "nm", "unknown", ""):
        raise ValueError(f"{hdr}: wavelength units {units!r} are not nm or µm")
    ignore = meta.get("data ignore value")
    if ignore is not None:
        cube = np.where(cube == np.float32(float(ignore)), np.float32(np.nan), cube)
    out = {"cube": cube, "wavelengths_nm": wl}
    if _extra_path(hdr).is_file():
        extra = read_npz(_extra_path(hdr), "cube extras file")
        out.update({k: v for k, v in extra.items() if k not in out})
    return out


# --- Zarr (one cube) --------------------------------------------------------------------
def _save_zarr(path: Path, cube, wl, extra) -> None:
    import xarray as xr

    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"cannot write {path}: folder {folder} does not exist")
    h, w, _ = cube.shape
    variables = {"reflectance": (("y", "x", "wavelength"), cube)}
    for k, v in extra.items():
        if v.dtype.kind == "U":  # variable-length strings: the type Zarr v3 specifies
            v = v.astype(object)
        if v.shape[:2] == (h, w):  # per-pixel maps keep the image axes
            dims = ("y", "x") + tuple(f"{k}_{i}" for i in range(v.ndim - 2))
            variables[k] = (dims, v)
        else:
            variables[k] = (tuple(f"{k}_{i}" for i in range(v.ndim)), v)
    ds = xr.Dataset(
        variables,
        coords={"wavelength": ("wavelength", wl, {"units": "nm"})},
        attrs={"description": "evhsi_jax reflectance cube"},
    )
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=folder))
    try:
        with warnings.catch_warnings():  # see _video_store.VideoStore.set_index
            warnings.simplefilter("ignore", UserWarning)
            ds.to_zarr(tmp / "store.zarr", mode="w", consolidated=True)
        if path.exists():  # replace: old aside, new in, old removed
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=folder))
            os.replace(path, old / "old.zarr")
            os.replace(tmp / "store.zarr", path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp / "store.zarr", path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _load_zarr(path: Path) -> dict:
    import xarray as xr

    if not path.is_dir():
        raise ValueError(f"cube store not found: {path}")
    try:
        ds = xr.open_zarr(path)
    except Exception as err:  # zarr/xarray raise many types for a bad store
        msg = one_line(err, 160)
        raise ValueError(f"{path} is not a readable Zarr cube ({msg})") from None
    with ds:
        if "reflectance" not in ds:
            raise ValueError(f"{path}: no 'reflectance' variable")
        refl = ds["reflectance"]
        if "time" in refl.dims:
            raise ValueError(
                f"{path} is a video store of {refl.sizes['time']} sweeps: read it "
                "with evhsi_jax.video.iter_sweep_cubes, or take one sweep with `evhsi "
                "convert STORE --sweep K OUT`"
            )
        out = {
            "cube": np.asarray(refl.transpose("y", "x", "wavelength").values),
            "wavelengths_nm": np.asarray(ds["wavelength"].values, np.float64),
        }
        for k in ds.data_vars:
            if k != "reflectance":
                v = np.asarray(ds[k].values)
                out[k] = np.array(v.tolist(), dtype=str) if v.dtype.kind in "OT" else v
    return out
