"""The per-sweep video store: one chunked, self-describing Zarr store, appended sweep by
sweep (`evhsi reconstruct --per-sweep --out VIDEO.zarr`).

**Layout** (Zarr v3, written with zarr-python, opened as a Dataset by
`xarray.open_zarr(path)`; one chunk per sweep, zstd-compressed with a CRC32C checksum so
a damaged chunk fails to read instead of returning wrong numbers):

- `reflectance` (time, y, x, wavelength) float32;
- `srgb` (time, y, x, rgb) uint8 preview; `events_per_pixel` (time, y, x) int32;
  `kkt` (time, y, x) float32;
- coordinates `wavelength` (nm, the channel centres) and `time` (the sweep's start,
  µs on the recording's clock), with `sweep`, `stop_us`, `events`,
  `pixels_solved` and `sweep_speed` (the mirror-speed factor the sweep was read with,
  NaN when none was measured: `--sweep-speed off`) per time step;
- root attribute `evhsi`: the run's index (the same object as a sweep folder's
  `index.json`, see :mod:`evhsi_jax._video._stream`); consolidated metadata, refreshed with
  the index (at most once a second while running, and at the end).

**Crash-safe and resumable.** zarr-python writes every chunk and metadata document
under a temporary name and renames it into place. Per sweep the arrays are appended in
a fixed order, `time` last, so the length of `time` is the number of complete sweeps;
on resume every array is cut back to it (a sweep in flight when the run died is
redone) and temporary `*.partial` files are removed. The folder is locked (an
advisory `flock` on the store directory itself, so the store holds no foreign file).
"""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import numpy as np

from .._base import one_line

__all__ = ["VideoStore", "is_video_store", "holds_video"]

_PER_PIXEL = (  # name, dtype, trailing axes
    ("reflectance", np.float32, ("y", "x", "wavelength")),
    ("srgb", np.uint8, ("y", "x", "rgb")),
    ("events_per_pixel", np.int32, ("y", "x")),
    ("kkt", np.float32, ("y", "x")),
)
_PER_SWEEP = ("sweep", "stop_us", "events", "pixels_solved")
#: Per-sweep float arrays (NaN: none). A store written before one existed lacks it,
#: and keeps lacking it when resumed (its lengths must follow `time`).
_PER_SWEEP_FLOAT = ("sweep_speed",)


def is_video_store(path) -> bool:
    """True for a path that names a video store (a `.zarr` folder)."""
    return Path(path).suffix.lower() == ".zarr"


def holds_video(path) -> bool:
    """True for an existing Zarr store with a `time` axis (a video, not one cube)."""
    path = Path(path)
    if not (is_video_store(path) and (path / "zarr.json").is_file()):
        return False
    try:
        import zarr

        group = zarr.open_group(str(path), mode="r", use_consolidated=False)
        return "time" in group
    except Exception:  # not a store: the cube reader names the problem
        return False


def _codecs():
    import zarr

    return [zarr.codecs.ZstdCodec(level=3), zarr.codecs.Crc32cCodec()]


class VideoStore:
    """A video store opened for appending (or reading).

    **Arguments:**

    - `path`: the `.zarr` folder (created when missing; its parent must exist).
    - `mode`: `"a"` to open or create for appending, `"r"` to read.
    """

    def __init__(self, path, mode: str = "a"):
        import zarr

        self.path = Path(path)
        if mode == "r" and not (self.path / "zarr.json").is_file():
            raise ValueError(f"{self.path} is not a video store (no zarr.json)")
        try:
            # The arrays themselves, not the consolidated summary (which lags them).
            self.group = zarr.open_group(str(self.path), mode=mode, use_consolidated=False)
        except Exception as err:  # zarr raises many types for a foreign folder
            msg = one_line(err, 160)
            raise ValueError(f"{self.path} is not a readable Zarr store ({msg})") from None
        self._lock_fd = None

    # --- locking ----------------------------------------------------------------------
    def lock(self) -> None:
        """Take the store's exclusive lock, or raise `ValueError` if another run holds
        it (released by the kernel when the process ends, however it ends)."""
        import fcntl

        fd = os.open(self.path, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ValueError(
                f"{self.path} is in use by another evhsi run; wait for it or use "
                "another store"
            ) from None
        self._lock_fd = fd

    def unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # --- index -------------------------------------------------------------------------
    @property
    def index(self) -> dict | None:
        return self.group.attrs.asdict().get("evhsi")

    def set_index(self, index: dict) -> None:
        """Store the run's index and refresh the consolidated metadata (what
        `xarray.open_zarr` reads first: it then shows the sweeps complete so far)."""
        import zarr

        self.group.attrs.update({"evhsi": index})
        with warnings.catch_warnings():  # zarr notes that v3 has no spec for it yet;
            warnings.simplefilter("ignore", UserWarning)  # xarray and zarr read it
            zarr.consolidate_metadata(str(self.path))

    # --- contents ----------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.group["time"].shape[0]) if "time" in self.group else 0

    def clear(self) -> None:
        """Remove every array and the index (start afresh)."""
        for name in list(self.group.array_keys()):
            shutil.rmtree(self.path / name, ignore_errors=True)
        self.group.attrs.update({"evhsi": None})

    def repair(self) -> int:
        """Cut every array back to the complete sweeps and delete temporary files of a
        killed run; returns the number of temporary files removed."""
        n = len(self)
        for name in self.group.array_keys():
            arr = self.group[name]
            if name != "wavelength" and arr.shape and arr.shape[0] > n:
                arr.resize((n, *arr.shape[1:]))
        stale = list(self.path.rglob("*.partial"))
        for f in stale:
            f.unlink(missing_ok=True)
        return len(stale)

    def entries(self) -> list[dict]:
        """Index entries of the complete sweeps, from the store's own arrays."""
        n = len(self)
        if n == 0:
            return []
        cols = {k: np.asarray(self.group[k][:n]) for k in _PER_SWEEP}
        floats = {k: np.asarray(self.group[k][:n]) for k in _PER_SWEEP_FLOAT
                  if k in self.group}  # fmt: skip
        start = np.asarray(self.group["time"][:n])
        out = []
        for i in range(n):
            entry = {
                "sweep": int(cols["sweep"][i]),
                "file": None,
                "position": i,
                "start_us": int(start[i]),
                "stop_us": int(cols["stop_us"][i]),
                "events": int(cols["events"][i]),
                "pixels_solved": int(cols["pixels_solved"][i]),
                "seconds": None,
            }
            entry.update({k: float(v[i]) for k, v in floats.items() if np.isfinite(v[i])})
            out.append(entry)
        return out

    def _create(self, h: int, w: int, wavelengths_nm) -> None:
        g = self.group
        wl = np.asarray(wavelengths_nm, np.float64)
        m = wl.size
        g.create_array("wavelength", data=wl, dimension_names=("wavelength",),
                       overwrite=True).attrs.update({"units": "nm"})  # fmt: skip
        sizes = {"y": h, "x": w, "wavelength": m, "rgb": 3}
        for name, dtype, axes in _PER_PIXEL:
            shape = tuple(sizes[a] for a in axes)
            g.create_array(
                name,
                shape=(0, *shape),
                chunks=(1, *shape),
                dtype=dtype,
                dimension_names=("time", *axes),
                compressors=_codecs(),
                overwrite=True,
            )
        for name in (*_PER_SWEEP, "time"):
            g.create_array(name, shape=(0,), chunks=(4096,), dtype=np.int64,
                           dimension_names=("time",), overwrite=True)  # fmt: skip
        for name in _PER_SWEEP_FLOAT:
            g.create_array(name, shape=(0,), chunks=(4096,), dtype=np.float64,
                           dimension_names=("time",), overwrite=True)  # fmt: skip
        g["reflectance"].attrs.update({"long_name": "reflectance", "units": "1"})
        g["time"].attrs.update(
            {"long_name": "sweep start", "units": "microseconds"}
        )

    def append(self, entry: dict, cube, srgb, events_per_pixel, kkt) -> None:
        """Append one sweep (the arrays first, `time` last: see the module doc)."""
        cube = np.asarray(cube, np.float32)
        h, w, _ = cube.shape
        if "time" not in self.group:
            raise ValueError("the store has no arrays yet: call prepare() first")
        values = {
            "reflectance": cube,
            "srgb": np.asarray(srgb, np.uint8),
            "events_per_pixel": np.asarray(events_per_pixel, np.int32),
            "kkt": np.asarray(kkt, np.float32),
        }
        for name, _, _ in _PER_PIXEL:
            self.group[name].append(values[name][None], axis=0)
        for name in _PER_SWEEP:
            self.group[name].append(np.array([entry[name]], np.int64))
        for name in _PER_SWEEP_FLOAT:
            if name in self.group:
                self.group[name].append(np.array([entry.get(name, np.nan)], np.float64))
        self.group["time"].append(np.array([entry["start_us"]], np.int64))

    def prepare(self, h: int, w: int, wavelengths_nm) -> None:
        """Create the arrays if the store has none; check them if it has."""
        if "time" not in self.group:
            self._create(h, w, wavelengths_nm)
            return
        shape = self.group["reflectance"].shape[1:]
        wl = np.asarray(self.group["wavelength"][:])
        if shape != (h, w, len(wavelengths_nm)) or not np.allclose(wl, wavelengths_nm):
            raise ValueError(
                f"{self.path} holds cubes of {shape}, not {(h, w, len(wavelengths_nm))}"
            )

    # --- reading -----------------------------------------------------------------------
    def cube_file(self, i: int) -> dict:
        """Sweep `i` (position in the store) as `load_cube` returns a cube file."""
        g = self.group
        return {
            "cube": np.asarray(g["reflectance"][i]),
            "wavelengths_nm": np.asarray(g["wavelength"][:], np.float64),
            "srgb": np.asarray(g["srgb"][i]),
            "events_per_pixel": np.asarray(g["events_per_pixel"][i]),
            "kkt": np.asarray(g["kkt"][i]),
            "sweep": np.int64(g["sweep"][i]),
            "start_us": np.int64(g["time"][i]),
            "stop_us": np.int64(g["stop_us"][i]),
            "events": np.int64(g["events"][i]),
        }
