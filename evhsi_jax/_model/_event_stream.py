"""The event stream container shared by the simulator, the file readers and the solver.

An :class:`EventStream` is plain NumPy (events are data, not differentiable leaves): the
columns `x`, `y`, `p` (1 = ON, 0 = OFF, as Prophesee), `t_us` (int64 microseconds), the
sensor geometry, and optional external triggers (e.g. a mirror encoder marking each
sweep start). The `.npz` layout is the contract of DESIGN.md.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt

from .._base import atomic_write, read_npz, scalar_int

__all__ = ["EventStream", "check_roi"]


def check_roi(roi, width: int, height: int) -> tuple[int, int, int, int]:
    """`roi` as `(x0, y0, x1, y1)` ints inside a `width` x `height` sensor, or a
    `ValueError` saying what is wrong (`x0 < x1 <= width`, `y0 < y1 <= height`)."""
    try:
        x0, y0, x1, y1 = (int(v) for v in roi)
    except (TypeError, ValueError):
        raise ValueError(f"a region is x0,y0,x1,y1 (4 integers), got {roi!r}") from None
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise ValueError(
            f"region {x0},{y0},{x1},{y1} is not inside the {width}x{height} sensor "
            "(need 0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height)"
        )
    return x0, y0, x1, y1


@dataclasses.dataclass(frozen=True, eq=False)
class EventStream:
    """A time-ordered stream of camera events.

    **Arguments:**

    - `x`, `y`: pixel coordinates, shape `(ev,)`, integers in `[0, width)`, `[0, height)`.
    - `p`: polarity, shape `(ev,)`, 1 for ON (brighter) and 0 for OFF.
    - `t_us`: timestamps in microseconds, shape `(ev,)`, int64, non-decreasing.
    - `width`, `height`: sensor geometry in pixels.
    - `trigger_t_us`, `trigger_p`, `trigger_id`: external trigger events (may be empty).
    """

    x: npt.ArrayLike
    y: npt.ArrayLike
    p: npt.ArrayLike
    t_us: npt.ArrayLike
    width: int
    height: int
    trigger_t_us: npt.ArrayLike = dataclasses.field(
        default_factory=lambda: np.zeros(0, np.int64)
    )
    trigger_p: npt.ArrayLike = dataclasses.field(
        default_factory=lambda: np.zeros(0, np.uint8)
    )
    trigger_id: npt.ArrayLike = dataclasses.field(
        default_factory=lambda: np.zeros(0, np.uint8)
    )

    def __post_init__(self):
        cast = {
            "x": np.uint16,
            "y": np.uint16,
            "p": np.uint8,
            "t_us": np.int64,
            "trigger_t_us": np.int64,
            "trigger_p": np.uint8,
            "trigger_id": np.uint8,
        }
        for name, dtype in cast.items():
            value = np.asarray(getattr(self, name))
            if value.ndim != 1:
                raise ValueError(
                    f"event column {name!r} must be 1-D, got {value.shape}"
                )
            if value.size and not np.issubdtype(value.dtype, np.integer):
                if value.dtype.kind not in "fb" or not np.array_equal(
                    value, np.round(value)
                ):  # NaN and text fail here too
                    raise ValueError(f"event column {name!r} must hold integers")
            if value.size:
                info = np.iinfo(dtype)
                if value.min() < info.min or value.max() > info.max:
                    raise ValueError(
                        f"event column {name!r} has values outside {dtype.__name__}"
                    )
            object.__setattr__(self, name, value.astype(dtype, copy=False))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        n = self.x.size
        for name in ("y", "p", "t_us"):
            if getattr(self, name).size != n:
                raise ValueError(
                    f"event columns differ in length: x has {n}, "
                    f"{name} has {getattr(self, name).size}"
                )
        if not (self.trigger_t_us.size == self.trigger_p.size == self.trigger_id.size):
            raise ValueError("trigger columns differ in length")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(
                f"sensor geometry must be positive, got {self.width}x{self.height}"
            )
        if n:
            if self.x.max() >= self.width or self.y.max() >= self.height:
                raise ValueError(
                    f"event coordinates outside the {self.width}x{self.height} geometry"
                )
            if self.p.max() > 1:
                raise ValueError("polarity must be 0 (OFF) or 1 (ON)")

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def polarity_sign(self) -> np.ndarray:
        """Polarity as ±1 (int8)."""
        return (2 * self.p.astype(np.int8) - 1).astype(np.int8)

    @property
    def duration_us(self) -> int:
        """Time from the first to the last event, in microseconds (0 if < 2 events)."""
        return int(self.t_us[-1] - self.t_us[0]) if len(self) > 1 else 0

    def is_time_ordered(self) -> bool:
        """Whether the times never decrease (a comparison of neighbours: no array of
        differences, 800 MB for the 100 M events of a 4-sweep 1280×720 recording)."""
        t = self.t_us
        return bool((t[1:] >= t[:-1]).all())

    def sorted_by_time(self) -> EventStream:
        """A copy in non-decreasing time order (stable: ties keep their order)."""
        if self.is_time_ordered():
            return self
        order = np.argsort(self.t_us, kind="stable")
        return self.take(order)

    def take(self, index) -> EventStream:
        """A new stream with the events selected by `index` (triggers kept)."""
        return dataclasses.replace(
            self,
            x=self.x[index],
            y=self.y[index],
            p=self.p[index],
            t_us=self.t_us[index],
        )

    def split(self, n: int) -> Iterator[EventStream]:
        """Consecutive parts of at most `n` events (at least one part, empty for an
        empty stream); the triggers go with the first part only."""
        for i in range(0, max(len(self), 1), max(1, n)):
            part = self.take(slice(i, i + n))
            if i:
                part = dataclasses.replace(
                    part,
                    trigger_t_us=part.trigger_t_us[:0],
                    trigger_p=part.trigger_p[:0],
                    trigger_id=part.trigger_id[:0],
                )
            yield part

    def crop(self, roi: tuple[int, int, int, int]) -> EventStream:
        """The events of the region `roi = (x0, y0, x1, y1)` (half-open, pixels), in
        the region's own coordinates (geometry `(x1 - x0) x (y1 - y0)`); triggers
        kept. See `check_roi`."""
        x0, y0, x1, y1 = check_roi(roi, self.width, self.height)
        keep = (self.x >= x0) & (self.x < x1) & (self.y >= y0) & (self.y < y1)
        return dataclasses.replace(
            self.take(keep),
            x=self.x[keep] - np.uint16(x0),
            y=self.y[keep] - np.uint16(y0),
            width=x1 - x0,
            height=y1 - y0,
        )

    def time_window(self, t0_us: int, t1_us: int) -> EventStream:
        """Events and triggers with `t0_us <= t_us < t1_us` (stream must be ordered)."""
        lo, hi = np.searchsorted(self.t_us, [t0_us, t1_us], side="left")
        tlo, thi = np.searchsorted(self.trigger_t_us, [t0_us, t1_us], side="left")
        return dataclasses.replace(
            self,
            x=self.x[lo:hi],
            y=self.y[lo:hi],
            p=self.p[lo:hi],
            t_us=self.t_us[lo:hi],
            trigger_t_us=self.trigger_t_us[tlo:thi],
            trigger_p=self.trigger_p[tlo:thi],
            trigger_id=self.trigger_id[tlo:thi],
        )

    @staticmethod
    def concatenate(streams: list[EventStream]) -> EventStream:
        """Join streams of one geometry, keeping time order (stable merge)."""
        if not streams:
            raise ValueError("nothing to concatenate")
        w, h = streams[0].width, streams[0].height
        if any((s.width, s.height) != (w, h) for s in streams):
            raise ValueError("cannot concatenate streams of different geometry")
        cat = {
            k: np.concatenate([getattr(s, k) for s in streams])
            for k in ("x", "y", "p", "t_us", "trigger_t_us", "trigger_p", "trigger_id")
        }
        out = EventStream(width=w, height=h, **cat)
        torder = np.argsort(out.trigger_t_us, kind="stable")
        out = dataclasses.replace(
            out,
            trigger_t_us=out.trigger_t_us[torder],
            trigger_p=out.trigger_p[torder],
            trigger_id=out.trigger_id[torder],
        )
        return out.sorted_by_time()

    # --- .npz, the contract format -------------------------------------------------
    def save_npz(self, path: str | os.PathLike) -> None:
        """Write the DESIGN.md `.npz` layout atomically (whole file or nothing)."""
        arrays = dict(
            x=self.x,
            y=self.y,
            p=self.p,
            t_us=self.t_us,
            width=np.int64(self.width),
            height=np.int64(self.height),
        )
        if self.trigger_t_us.size:
            arrays.update(
                trigger_t_us=self.trigger_t_us,
                trigger_p=self.trigger_p,
                trigger_id=self.trigger_id,
            )
        atomic_write(path, lambda f: np.savez(f, **arrays))

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> EventStream:
        """Read an events `.npz`; a clear `ValueError` when keys or values are wrong."""
        path = Path(path)
        data = read_npz(path, "events file")
        missing = [k for k in ("x", "y", "p", "t_us") if k not in data]
        if missing:
            raise ValueError(f"{path} lacks event keys {missing}")
        cols = {k: data[k] for k in ("x", "y", "p", "t_us")}
        for k, v in cols.items():
            if v.ndim != 1 or not (
                np.issubdtype(v.dtype, np.integer) or np.issubdtype(v.dtype, np.floating)
            ):
                raise ValueError(f"{path}: {k!r} must be a 1-D numeric column")
        if "width" in data and "height" in data:
            width, height = (scalar_int(data, k, path) for k in ("width", "height"))
        elif cols["x"].size:
            width, height = int(cols["x"].max()) + 1, int(cols["y"].max()) + 1
        else:
            raise ValueError(f"{path} has no events and no width/height")
        trig = {}
        if "trigger_t_us" in data:
            trig = {
                k: data[k]
                for k in ("trigger_t_us", "trigger_p", "trigger_id")
                if k in data
            }
            n = trig["trigger_t_us"].size
            trig.setdefault("trigger_p", np.ones(n, np.uint8))
            trig.setdefault("trigger_id", np.zeros(n, np.uint8))
        if cols["p"].size and np.issubdtype(cols["p"].dtype, np.signedinteger):
            if cols["p"].min() < 0:  # accept ±1 polarity and map it to 1/0
                cols["p"] = (cols["p"] > 0).astype(np.uint8)
        for k in ("x", "y", "t_us"):
            if cols[k].size and np.issubdtype(cols[k].dtype, np.integer):
                if cols[k].min() < 0:
                    raise ValueError(f"{path}: negative values in {k!r}")
        try:
            stream = cls(width=width, height=height, **cols, **trig)
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
        if not stream.is_time_ordered():
            raise ValueError(f"{path}: events are not in time order")
        return stream
