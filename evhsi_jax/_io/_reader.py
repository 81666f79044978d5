"""Reading event files: format detection, bounded-memory streaming, time windows.

`EventReader` opens a `.raw` (EVT 3.0 or EVT 2.0, told apart by the header) or `.npz`
file and hands out `EventStream` chunks. Raw files are read `chunk_bytes` at a time; the
decoder state (row, vector base, time base, wrap count, running maximum) is carried from
chunk to chunk, so memory stays bounded by the chunk size and the result does not depend
on where chunks are cut (nor on the number of decoding threads, nor on whether the
compiled kernels or the NumPy reference decode them; see `_decode` and `_numba`).

A time window `[t0, t1)` is read without decoding the whole file: the first window read
makes one cheap pass that advances the decoder state without expanding events and
records, for each chunk, its file offset, the state at its start and the time range of
its events and triggers (the running maximum makes these ranges tight). Later reads seek
straight to the chunks that overlap the window and decode only those.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .._model import EventStream
from ._chunks import DecodedChunk, as_stream
from ._decode import CODECS, decode_chunks, decode_range
from ._evt2 import Evt2State
from ._evt3_decode import Evt3State
from ._header import DEFAULT_GEOMETRY, MAX_HEADER_BYTES, RawHeader, parse_header
from ._report import DecodeReport

__all__ = [
    "EventReader",
    "open_events",
    "read_events",
    "iter_events",
    "read_events_window",
    "DEFAULT_CHUNK_BYTES",
]

DEFAULT_CHUNK_BYTES = 1 << 19  # 512 KiB: temporaries stay in cache (fastest here)
PIPELINE_MIN_CHUNK = 1 << 16  # below this, thread hand-offs cost more than they save
_FORMATS = ("evt3", "evt2")


@dataclasses.dataclass(frozen=True)
class _Checkpoint:
    offset: int
    nbytes: int
    state: Evt3State | Evt2State
    t_lo: int  # running maximum of event times before the chunk
    t_hi: int  # ... and after it
    g_lo: int  # the same for triggers
    g_hi: int
    n_events: int
    n_triggers: int


class EventReader:
    """A streaming reader for one event file.

    **Arguments:**

    - `path`: a `.raw` (Prophesee EVT 3.0 or EVT 2.0) or `.npz` (DESIGN.md layout) file.
    - `chunk_bytes`: bytes decoded per chunk when iterating (raw files); bounds memory.
      `read()` and `read_window()` with the compiled kernels decode their byte range
      in one call (results as if chunked; the input is memory-mapped).
    - `strict`: raise `ValueError` on the first defect instead of skipping and counting
      it in `report` (see `DecodeReport`).
    - `geometry`: `(width, height)` overriding the header (raw files).
    - `format`: `"evt3"` or `"evt2"`, overriding the header; needed for a raw file whose
      header does not name its format.
    - `workers`: decoding threads of the NumPy path (`EVHSI_NO_NUMBA=1`; the compiled
      kernels decode on the calling thread); `None` uses two for chunks of 64 KiB and
      more when there are at least four of them (the result does not depend on it, see
      `_decode`).

    After reading, `report` holds the counts of what was decoded and skipped.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        strict: bool = False,
        geometry: tuple[int, int] | None = None,
        format: str | None = None,
        workers: int | None = None,
    ) -> None:
        self.path = Path(path)
        self.workers = workers
        if not self.path.is_file():
            raise ValueError(f"event file not found: {self.path}")
        if chunk_bytes < 1:
            raise ValueError(f"chunk_bytes must be positive, got {chunk_bytes}")
        self.chunk_bytes = int(chunk_bytes)
        self.strict = bool(strict)
        self.report = DecodeReport()
        self.header: RawHeader | None = None
        self._index: list[_Checkpoint] | None = None
        self._npz: EventStream | None = None
        suffix = self.path.suffix.lower()
        if suffix == ".npz":
            self.format = "npz"
            self._npz = EventStream.load_npz(self.path)
            self.width, self.height = self._npz.width, self._npz.height
            self.geometry_source = "npz"
            self.data_offset = 0
            return
        if suffix != ".raw":
            raise ValueError(
                f"{self.path}: unknown event file extension {suffix!r} "
                "(expected .raw or .npz)"
            )
        self.header = self._read_header()
        fmt = format or self.header.format
        if self.header.size == 0 and format is None:
            raise ValueError(
                f"{self.path}: no Prophesee header ('% key value' lines); "
                "not an EVT .raw file (pass format='evt3' or 'evt2' to force)"
            )
        if fmt is None:
            raise ValueError(
                f"{self.path}: header names no event format ('% evt 3.0' or "
                "'% format EVT3'); pass format='evt3' or 'evt2'"
            )
        if fmt not in _FORMATS:
            raise ValueError(f"{self.path}: event format {fmt!r} is not supported")
        self.format = fmt
        if geometry is not None:
            self.width, self.height = (int(v) for v in geometry)
            self.geometry_source = "argument"
        elif self.header.width is not None:
            self.width, self.height = self.header.geometry()
            self.geometry_source = "header"
        else:
            self.width, self.height = DEFAULT_GEOMETRY
            self.geometry_source = "default"
        if self.width <= 0 or self.height <= 0:
            raise ValueError(
                f"geometry must be positive, got {self.width}x{self.height}"
            )
        self.data_offset = self.header.size
        self.file_bytes = self.path.stat().st_size

    def _read_header(self) -> RawHeader:
        """Parse the header, reading only as much of the file as it takes."""
        size = 4096
        with open(self.path, "rb") as f:
            while True:
                f.seek(0)
                head = f.read(size)
                at_eof = len(head) < size
                try:
                    header = parse_header(head, at_eof=at_eof)
                except ValueError as err:
                    if at_eof or size > MAX_HEADER_BYTES:
                        raise ValueError(f"{self.path}: {err}") from None
                    header = None
                if header is not None and (at_eof or header.size < len(head)):
                    return header
                if size > MAX_HEADER_BYTES:
                    raise ValueError(
                        f"{self.path}: header is longer than {MAX_HEADER_BYTES} bytes"
                    )
                size *= 4

    # --- decoding ---
    @property
    def word_bytes(self) -> int:
        """Bytes per data word (2 for EVT 3.0, 4 for EVT 2.0)."""
        return CODECS[self.format].word_bytes

    def _new_state(self) -> Evt3State | Evt2State:
        return CODECS[self.format].new_state()

    def _decoded(
        self,
        offset: int,
        state: Evt3State | Evt2State,
        report: DecodeReport,
        *,
        stop: int | None = None,
        **kwargs,
    ) -> Iterator[tuple]:
        """`decode_chunks` over `[offset, stop)` with this reader's settings."""
        stop = self.file_bytes if stop is None else stop
        return decode_chunks(
            self.path,
            CODECS[self.format],
            offset,
            stop,
            state,
            report,
            **self._settings(offset, stop),
            **kwargs,
        )

    def _settings(self, offset: int, stop: int) -> dict:
        workers = self.workers
        if workers is None:  # threads pay off for large chunks of large ranges
            big = self.chunk_bytes >= PIPELINE_MIN_CHUNK
            many = stop - offset >= 4 * self.chunk_bytes
            workers = min(2, os.cpu_count() or 1) if big and many else 1
        return dict(
            chunk_bytes=self.chunk_bytes,
            width=self.width,
            height=self.height,
            strict=self.strict,
            workers=workers,
        )

    def _range(
        self, offset: int, stop: int, state: Evt3State | Evt2State
    ) -> EventStream:
        """`[offset, stop)` decoded as one stream, into `self.report`."""
        self.report = DecodeReport()
        chunk = decode_range(
            self.path,
            CODECS[self.format],
            offset,
            stop,
            state,
            self.report,
            **self._settings(offset, stop),
        )
        return self._stream(chunk)

    def _stream(self, c: DecodedChunk) -> EventStream:
        return as_stream(c, self.width, self.height)

    def __iter__(self) -> Iterator[EventStream]:
        """Chunks of the file in order, each an `EventStream` (empty chunks skipped)."""
        if self._npz is not None:
            for part in self._npz.split(max(1, self.chunk_bytes // 2)):
                if len(part) or part.trigger_t_us.size:
                    yield part
            return
        self.report = DecodeReport()
        for *_, c in self._decoded(self.data_offset, self._new_state(), self.report):
            if c.x.size or c.trigger_t_us.size:
                yield self._stream(c)

    def follow(
        self,
        *,
        idle_timeout_s: float = 10.0,
        poll_s: float = 0.02,
        should_stop=None,
    ) -> Iterator[EventStream]:
        """Chunks of a `.raw` file that a recorder is still writing, as they arrive.

        Decodes the whole data words present, then waits for more (polling the file
        size every `poll_s`), carrying the decoder state, so the chunks equal those of
        reading the finished file. Ends when the file has not grown for
        `idle_timeout_s` seconds, or when `should_stop()` (checked while waiting)
        returns True; a partial word left at the end counts as `trailing_bytes`.
        """
        import time

        if self._npz is not None:
            raise ValueError(f"{self.path}: only .raw recordings can be followed")
        codec = CODECS[self.format]
        word = codec.word_bytes
        self.report = DecodeReport()
        state, offset = self._new_state(), self.data_offset
        last_growth = time.monotonic()
        while True:
            size = self.path.stat().st_size
            stop = offset + (size - offset) // word * word
            if stop > offset:
                for *_, c in decode_chunks(
                    self.path, codec, offset, stop, state, self.report,
                    **{**self._settings(offset, stop), "workers": 1},
                ):  # fmt: skip
                    if c.x.size or c.trigger_t_us.size:
                        yield self._stream(c)
                offset = stop
                last_growth = time.monotonic()
                continue
            idle = time.monotonic() - last_growth
            if idle >= idle_timeout_s or (should_stop is not None and should_stop()):
                self.report.trailing_bytes += size - offset
                self.file_bytes = size
                return
            time.sleep(poll_s)

    def read(self) -> EventStream:
        """The whole file as one `EventStream`."""
        if self._npz is not None:
            return self._npz
        return self._range(self.data_offset, self.file_bytes, self._new_state())

    # --- time windows ---
    def build_index(self) -> None:
        """One cheap pass recording each chunk's start state and time range."""
        if self._npz is not None or self._index is not None:
            return
        index = []
        state = self._new_state()
        report = DecodeReport()  # the pass's own: `self.report` describes reads
        for offset, nbytes, before, (n_events, n_triggers) in self._decoded(
            self.data_offset, state, report, expand=False, snapshots=True
        ):
            index.append(
                _Checkpoint(
                    offset=offset,
                    nbytes=nbytes,
                    state=before,
                    t_lo=before.last_t,
                    t_hi=state.last_t,
                    g_lo=before.last_trig_t,
                    g_hi=state.last_trig_t,
                    n_events=n_events,
                    n_triggers=n_triggers,
                )
            )
        self._index = index

    def read_window(
        self, t0_us: int | np.integer, t1_us: int | np.integer
    ) -> EventStream:
        """Events and triggers with `t0_us <= t < t1_us`, decoding only chunks that
        overlap the window (after a one-time index pass; see the module doc).

        **Arguments:**

        - `t0_us`, `t1_us`: window bounds in µs (decoded, wrap-extended time).

        **Returns:** the same as `read().time_window(t0_us, t1_us)`.
        """
        t0_us, t1_us = int(t0_us), int(t1_us)
        if self._npz is not None:
            return self._npz.time_window(t0_us, t1_us)
        self.build_index()
        wanted = [
            i
            for i, cp in enumerate(self._index)
            if (cp.n_events and cp.t_hi >= t0_us and cp.t_lo < t1_us)
            or (cp.n_triggers and cp.g_hi >= t0_us and cp.g_lo < t1_us)
        ]
        if not wanted:
            self.report = DecodeReport()
            return self._stream(DecodedChunk.empty())
        # A contiguous run of chunks (times only grow): decode it.
        first, last = self._index[wanted[0]], self._index[wanted[-1]]
        stop = last.offset + last.nbytes
        part = self._range(first.offset, stop, first.state.copy())
        return part.time_window(t0_us, t1_us)


def open_events(path: str | os.PathLike, **kwargs) -> EventReader:
    """Open an event file for streaming (`EventReader`; same keyword arguments)."""
    return EventReader(path, **kwargs)


def read_events(
    path: str | os.PathLike,
    *,
    strict: bool = False,
    geometry: tuple[int, int] | None = None,
    format: str | None = None,
) -> EventStream:
    """Read a whole event file by extension: `.raw` (EVT 3.0 / 2.0 by header) or `.npz`.

    **Arguments:**

    - `path`: the file.
    - `strict`, `geometry`, `format`: see `EventReader`.

    **Returns:** the `EventStream` (time-ordered; defects skipped unless `strict`).
    """
    return EventReader(path, strict=strict, geometry=geometry, format=format).read()


def iter_events(
    path: str | os.PathLike,
    *,
    chunk_bytes: int = DEFAULT_CHUNK_BYTES,
    strict: bool = False,
    geometry: tuple[int, int] | None = None,
    format: str | None = None,
) -> Iterator[EventStream]:
    """Stream an event file as `EventStream` chunks with bounded memory.

    **Arguments:** as for `EventReader`.

    **Returns:** an iterator of chunks whose concatenation is `read_events(path)`.
    """
    yield from EventReader(
        path, chunk_bytes=chunk_bytes, strict=strict, geometry=geometry, format=format
    )


def read_events_window(
    path: str | os.PathLike,
    t0_us: int | np.integer,
    t1_us: int | np.integer,
    *,
    strict: bool = False,
    geometry: tuple[int, int] | None = None,
    format: str | None = None,
) -> EventStream:
    """Events and triggers with `t0_us <= t < t1_us` (see `EventReader.read_window`).

    **Arguments:**

    - `path`: the file; `t0_us`, `t1_us`: window in µs; the rest as for `EventReader`.

    **Returns:** equal to `read_events(path).time_window(t0_us, t1_us)`.
    """
    reader = EventReader(path, strict=strict, geometry=geometry, format=format)
    return reader.read_window(t0_us, t1_us)
