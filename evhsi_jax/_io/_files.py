"""Event files by extension: write, convert, describe (`evhsi info`, `convert`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .._model import EventStream
from ._evt3_encode import write_evt3
from ._reader import DEFAULT_CHUNK_BYTES, EventReader

__all__ = ["write_events", "convert_events", "describe_events", "replay_raw"]


def write_events(
    path: str | os.PathLike, events: EventStream, *, reorder: bool = False
) -> None:
    """Write an event file by extension: `.raw` (EVT 3.0) or `.npz`, atomically.

    **Arguments:**

    - `path`: destination, `.raw` or `.npz`.
    - `events`: the stream.
    - `reorder`: `.raw` only, see `write_evt3`.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".raw":
        write_evt3(path, events, reorder=reorder)
    elif suffix == ".npz":
        events.sorted_by_time().save_npz(path)
    else:
        raise ValueError(
            f"cannot write {path}: unknown event file extension {suffix!r} "
            "(expected .raw or .npz)"
        )


def convert_events(
    src: str | os.PathLike, dst: str | os.PathLike, *, strict: bool = False
) -> dict:
    """Convert between event formats by extension (`.raw` EVT 3.0/2.0 → `.raw`/`.npz`).

    **Arguments:**

    - `src`: input file; `dst`: output file (written atomically).
    - `strict`: see `EventReader`.

    **Returns:** the decode report of `src` as a dict (what was skipped, if anything).
    """
    if Path(dst).suffix.lower() not in (".raw", ".npz"):
        raise ValueError(f"cannot write {dst}: expected a .raw or .npz file name")
    reader = EventReader(src, strict=strict)
    write_events(dst, reader.read())
    return reader.report.as_dict()


def describe_events(
    path: str | os.PathLike,
    *,
    strict: bool = False,
    chunk_bytes: int = DEFAULT_CHUNK_BYTES,
) -> dict:
    """Summarise an event file with bounded memory (streams it chunk by chunk).

    **Arguments:**

    - `path`: `.raw` or `.npz` event file.
    - `strict`, `chunk_bytes`: see `EventReader`.

    **Returns:** a JSON-ready dict: `format`, `width`, `height`, `geometry_source`,
    `events`, `triggers`, `t_first_us`, `t_last_us`, `duration_us`, `rate_ev_per_s`,
    `on_events`, `off_events`, `on_fraction`, `x_max`, `y_max` (observed extent),
    `file_bytes`, `bytes_per_event`, `header` (raw: the `% key value` fields) and
    `decode` (raw: the `DecodeReport` counters).
    """
    reader = EventReader(path, strict=strict, chunk_bytes=chunk_bytes)
    n = n_on = n_trig = 0
    t_first = t_last = None
    x_max = y_max = -1
    for chunk in reader:
        n_trig += int(chunk.trigger_t_us.size)
        if not len(chunk):
            continue
        n += len(chunk)
        n_on += int(np.count_nonzero(chunk.p))
        t_first = int(chunk.t_us[0]) if t_first is None else t_first
        t_last = int(chunk.t_us[-1])
        x_max = max(x_max, int(chunk.x.max()))
        y_max = max(y_max, int(chunk.y.max()))
    size = Path(path).stat().st_size
    duration = (t_last - t_first) if n > 1 else 0
    info = {
        "path": str(path),
        "format": reader.format,
        "width": reader.width,
        "height": reader.height,
        "geometry_source": reader.geometry_source,
        "events": n,
        "triggers": n_trig,
        "t_first_us": t_first,
        "t_last_us": t_last,
        "duration_us": duration,
        "rate_ev_per_s": (n / (duration * 1e-6)) if duration > 0 else None,
        "on_events": n_on,
        "off_events": n - n_on,
        "on_fraction": (n_on / n) if n else None,
        "x_max": x_max if n else None,
        "y_max": y_max if n else None,
        "file_bytes": size,
        "bytes_per_event": (size / n) if n else None,
    }
    if reader.header is not None:
        info["header"] = dict(reader.header.fields)
        info["decode"] = reader.report.as_dict()
    return info


def replay_raw(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    speed: float = 1.0,
    chunk_bytes: int = 4096,
) -> list[tuple[float, int]]:
    """Write a `.raw` recording to `dst` the way a recorder would: the header first,
    then each block of data words when its last event is due (event time / `speed`
    after the start, on the wall clock). For testing live reconstruction
    (`reconstruct_sweeps(..., follow=True)`); `dst` is written in place, not
    atomically, on purpose.

    **Returns:** `(wall_time, last_event_us)` after each block written
    (`time.time()` seconds): what latency measurements compare against.
    """
    import time

    if speed <= 0:
        raise ValueError(f"speed must be > 0, got {speed}")
    reader = EventReader(src, chunk_bytes=chunk_bytes, workers=1)
    if reader.format not in ("evt3", "evt2"):
        raise ValueError(f"{src}: only .raw recordings can be replayed")
    reader.build_index()
    data = Path(src).read_bytes()
    marks = []
    with open(dst, "wb") as f:
        f.write(data[: reader.data_offset])
        f.flush()
        start, t0 = time.time(), None
        for cp in reader._index:
            if cp.n_events:
                t0 = cp.t_lo if t0 is None else t0
                delay = start + (cp.t_hi - t0) / 1e6 / speed - time.time()
                if delay > 0:
                    time.sleep(delay)
            f.write(data[cp.offset : cp.offset + cp.nbytes])
            f.flush()
            marks.append((time.time(), int(cp.t_hi)))
        f.write(data[reader.data_offset + sum(c.nbytes for c in reader._index) :])
    return marks
