"""A calibration: the rig plus everything measured per pixel, as one object and one file
pair.

`evhsi calibrate` writes `CALIB.json` (every rig key, the sensor noise it measured in the
rig's sensor keys, and a `calibration` report) and a sibling `CALIB_thresholds.npz`
(per-pixel `threshold_on`, `threshold_off`, `hot_pixels`) that the JSON names under
`threshold_map`. :func:`load_calibration` reads both; :func:`evhsi_jax.reconstruct`
takes the result and uses all of it — the same cube as `evhsi reconstruct --calib`.
A plain :class:`Rig` has no per-pixel maps; `Rig.load` refuses a calibration file that
names maps (they would be silently lost).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._base import atomic_write, read_npz
from ._rig import Rig

__all__ = ["Calibration", "load_calibration"]


@dataclasses.dataclass(frozen=True, eq=False)
class Calibration:
    """A rig with the per-pixel maps and sensor noise a calibration measured.

    **Fields:**

    - `rig`: the fitted rig; its sensor keys (`threshold_noise`,
      `timestamp_jitter_us`, `photoreceptor_hz`, `noise_rate_hz`) hold the noise the
      calibration measured, which the reconstruction weights its rows with.
    - `threshold_on`, `threshold_off`: per-pixel thresholds `(H, W)`, log units, or
      `None` (the rig's global pair everywhere).
    - `hot_pixels`: `(H, W)` bool, pixels that fire without light, or `None`.
    - `report`: what the calibration measured and how well the fit went (JSON-able).
    """

    rig: Rig
    threshold_on: np.ndarray | None = None
    threshold_off: np.ndarray | None = None
    hot_pixels: np.ndarray | None = None
    report: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if (self.threshold_on is None) != (self.threshold_off is None):
            raise ValueError("give both threshold maps or neither")
        shape = None
        for name in ("threshold_on", "threshold_off", "hot_pixels"):
            a = getattr(self, name)
            if a is None:
                continue
            a = np.asarray(a, bool if name == "hot_pixels" else np.float64)
            if a.ndim != 2 or (shape is not None and a.shape != shape):
                raise ValueError(f"{name} map must be (H, W) like the others")
            if name != "hot_pixels" and (not np.all(np.isfinite(a)) or np.any(a <= 0)):
                raise ValueError(f"{name} map must be finite and > 0")
            shape = a.shape
            object.__setattr__(self, name, a)

    @property
    def shape(self) -> tuple[int, int] | None:
        """`(H, W)` of the maps, or `None` without maps."""
        for a in (self.threshold_on, self.hot_pixels):
            if a is not None:
                return a.shape
        return None

    def crop(self, roi: tuple[int, int, int, int], width: int) -> Calibration:
        """The calibration of the region `roi = (x0, y0, x1, y1)` (half-open, pixels)
        of a `width`-column sensor: the columns keep their own time offsets, the maps
        are cut to the region."""
        x0, y0, x1, y1 = (int(v) for v in roi)
        offs = np.asarray(self.rig.column_offsets(width), np.float64)[x0:x1]
        rig = self.rig.with_leaves(
            column_offsets_us=jnp.asarray(offs, self.rig.fwhm_nm.dtype)
        )
        cut = lambda a: None if a is None else a[y0:y1, x0:x1]  # noqa: E731
        return Calibration(
            rig,
            cut(self.threshold_on),
            cut(self.threshold_off),
            cut(self.hot_pixels),
            {**self.report, "roi": [x0, y0, x1, y1]},
        )

    def with_channels(self, channels: int) -> Calibration:
        """The calibration recovering `channels` channels (:meth:`Rig.with_channels`);
        the per-pixel maps, hot pixels and report are the channel count's alike."""
        return dataclasses.replace(self, rig=self.rig.with_channels(channels))

    def check_size(self, height: int, width: int) -> None:
        if self.shape is not None and self.shape != (height, width):
            raise ValueError(
                f"the calibration's per-pixel maps are {self.shape[0]}x{self.shape[1]}, "
                f"the recording is {height}x{width}"
            )

    @staticmethod
    def maps_path(path: str | os.PathLike) -> Path:
        """The maps file that :meth:`save` writes beside the JSON `path`."""
        path = Path(path)
        return path.with_name(path.stem + "_thresholds.npz")

    def save(self, path: str | os.PathLike) -> dict:
        """Write `path` (JSON) and, if there are maps, `<stem>_thresholds.npz` beside
        it; both atomic. Returns the JSON object written."""
        path = Path(path)
        cfg: dict[str, Any] = self.rig.to_dict()
        cfg["threshold_map"] = None
        if self.shape is not None:
            map_path = self.maps_path(path)
            arrays = {}
            if self.threshold_on is not None:
                arrays["threshold_on"] = self.threshold_on
                arrays["threshold_off"] = self.threshold_off
            if self.hot_pixels is not None:
                arrays["hot_pixels"] = self.hot_pixels
            atomic_write(map_path, lambda f: np.savez(f, **arrays))
            cfg["threshold_map"] = map_path.name
        if self.report:
            cfg["calibration"] = self.report
            if "comment" in self.report:
                cfg["comment"] = self.report["comment"]
        text = json.dumps(cfg, indent=2) + "\n"
        atomic_write(path, lambda f: f.write(text.encode()))
        return cfg


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration (or plain rig) JSON file and the per-pixel maps it names.

    Any rig key left out takes its default, so a one-key file is a valid calibration
    (global thresholds, no maps)."""
    path = Path(path)
    rig, data = Rig.load_file(path, maps="ignore")
    report = data.get("calibration") or {}
    on = off = hot = None
    name = data.get("threshold_map")
    if name is not None:
        if not isinstance(name, str):
            raise ValueError(
                f"{path}: rig key 'threshold_map' must be null or a file name"
            )
        mpath = Path(name)
        if not mpath.is_absolute():
            mpath = path.parent / mpath
        if not mpath.is_file():
            raise ValueError(f"{path}: threshold map file not found: {mpath}")
        maps = read_npz(mpath, "threshold map file")
        try:
            if {"threshold_on", "threshold_off"} <= set(maps):
                on = np.asarray(maps["threshold_on"], np.float64)
                off = np.asarray(maps["threshold_off"], np.float64)
            if "hot_pixels" in maps:
                hot = np.asarray(maps["hot_pixels"], bool)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{mpath}: maps must be numeric ({err})") from None
        if on is None and hot is None:
            raise ValueError(
                f"{mpath} holds neither threshold_on/threshold_off nor hot_pixels"
            )
    try:
        return Calibration(rig, on, off, hot, report)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
