"""Running a decoder over a file's chunks: in turn, or on two threads.

Each chunk goes through three steps (see `_chunks`): a per-word *scan* (format-specific),
`apply_time` (absolute, non-decreasing times; cheap and strictly in chunk order) and the
per-event `expand_events`. A scan needs the decoder state at its chunk's start, but only
the parts that the previous chunk's *last* words decide (row, vector base, TIME_HIGH,
time within the epoch): `carry_*_state` predicts them from the tail of the previous
chunk without scanning it, so with `workers >= 2` the scans and expansions of
consecutive chunks run in parallel threads (NumPy releases the GIL in its loops), while
the main thread reads the file, predicts states and applies the time fix-ups in order.
The wrap count and the running maxima are settled in `apply_time`, so the result — and
the report — are the same as decoding the chunks one after the other.

With the compiled kernels (`_numba`, the default) a chunk is decoded in one sequential
pass on the calling thread instead (the state goes in and comes out of the kernel), and
`decode_range` decodes a whole byte range in one call into arrays sized once, which
avoids concatenating chunks; `workers` then has no effect.
"""

from __future__ import annotations

import contextlib
import dataclasses
import mmap
import os
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .._base import numba_kernels as _numba
from ._chunks import DecodedChunk, ScannedChunk, apply_time, expand_events
from ._evt2 import Evt2State, carry_evt2_state, scan_evt2_words
from ._evt3_decode import Evt3State, carry_evt3_state, scan_evt3_words
from ._report import DecodeError, DecodeReport

__all__ = ["Codec", "CODECS", "decode_chunks", "decode_range"]


@dataclasses.dataclass(frozen=True)
class Codec:
    """The per-format pieces the pipeline needs."""

    key: str
    name: str
    word_bytes: int
    dtype: str
    epoch_bits: int
    new_state: Callable
    scan: Callable
    carry: Callable


CODECS = {
    "evt3": Codec(
        "evt3", "EVT 3.0", 2, "<u2", 24, Evt3State, scan_evt3_words, carry_evt3_state
    ),
    "evt2": Codec(
        "evt2", "EVT 2.0", 4, "<u4", 34, Evt2State, scan_evt2_words, carry_evt2_state
    ),
}


def _read_words(
    path: Path,
    codec: Codec,
    offset: int,
    stop: int,
    chunk_bytes: int,
    report: DecodeReport,
    strict: bool,
) -> Iterator[tuple[int, np.ndarray]]:
    """`(file offset, words)` per chunk; a word cut by a chunk boundary is carried
    over, a partial word at the end is a defect."""
    wb = codec.word_bytes
    with open(path, "rb") as f:
        f.seek(offset)
        pos, carry = offset, b""
        while pos < stop:
            buf = f.read(min(chunk_bytes, stop - pos))
            if not buf:
                break
            pos += len(buf)
            if carry:
                buf = carry + buf
            nfull = len(buf) // wb * wb
            carry = buf[nfull:]
            yield pos - len(buf), np.frombuffer(buf, codec.dtype, count=nfull // wb)
    if carry:
        if strict:
            raise DecodeError(
                f"{path}: file ends with {len(carry)} byte(s) of a partial "
                f"{8 * wb}-bit word (strict mode)"
            )
        report.trailing_bytes += len(carry)


def _merge(into: DecodeReport, part: DecodeReport) -> None:
    for f in dataclasses.fields(DecodeReport):
        a, b = getattr(into, f.name), getattr(part, f.name)
        setattr(into, f.name, max(a, b) if f.name == "max_step_back_us" else a + b)


def decode_chunks(
    path: Path,
    codec: Codec,
    offset: int,
    stop: int,
    state,
    report: DecodeReport,
    *,
    chunk_bytes: int,
    width: int,
    height: int,
    strict: bool = False,
    workers: int = 1,
    expand: bool = True,
    snapshots: bool = False,
) -> Iterator[tuple]:
    """Decode the chunks of `path[offset:stop]`, in file order.

    **Arguments:**

    - `path`, `codec`: the file and its format.
    - `offset`, `stop`: byte range of data words.
    - `state`: decoder state at `offset` (absolute epoch and maxima); updated.
    - `report`: counters, updated.
    - `chunk_bytes`, `width`, `height`, `strict`: see `EventReader`.
    - `workers`: threads (1: everything in turn on the calling thread).
    - `expand`: when False, yield `(event words that keep their events, triggers)`
      instead of decoded events (indexing needs no events; geometry is not checked).
    - `snapshots`: yield a copy of the state at each chunk's start (serial only).

    **Returns:** an iterator of `(offset, nbytes, state_before, chunk)`.
    """
    words = _read_words(path, codec, offset, stop, chunk_bytes, report, strict)
    if _numba.use_numba():
        yield from _decode_chunks_jit(
            path, codec, words, state, report, width, height, strict, expand, snapshots
        )
        return

    def scan(w: np.ndarray, st, r: DecodeReport, at: int) -> ScannedChunk:
        try:
            return codec.scan(w, st, report=r, strict=strict, byte_offset=at)
        except DecodeError as err:
            raise DecodeError(f"{path}: {err}") from None

    def finish(sc: ScannedChunk, r: DecodeReport) -> DecodedChunk:
        try:
            return expand_events(
                sc,
                width=width,
                height=height,
                report=r,
                strict=strict,
                word_bytes=codec.word_bytes,
                fmt=codec.name,
            )
        except DecodeError as err:
            raise DecodeError(f"{path}: {err}") from None

    if workers <= 1 or snapshots or not expand:
        for at, w in words:
            before = state.copy() if snapshots else None
            epoch = state.epoch
            sc = scan(w, state, report, at)
            sc = apply_time(sc, epoch << codec.epoch_bits, state, report)
            yield at, w.nbytes, before, finish(sc, report) if expand else _counts(sc)
        return

    # Parallel: scans are submitted with predicted start states; `apply_time` and the
    # state bookkeeping run here, in chunk order; expansions go back to the pool.
    with ThreadPoolExecutor(max_workers=workers) as pool:
        scans: deque = deque()
        done: deque = deque()
        predicted = state.copy()

        def settle_oldest() -> None:
            at, nbytes, fut, r, after = scans.popleft()
            try:
                sc = fut.result()
            except DecodeError:
                for _, _, f, _ in done:  # an earlier chunk's error comes first
                    f.result()
                raise
            sc = apply_time(sc, state.epoch << codec.epoch_bits, state, r)
            for name in ("y", "base_x", "vpol", "th", "time"):
                if hasattr(after, name):
                    setattr(state, name, getattr(after, name))
            state.epoch += sc.wraps
            done.append((at, nbytes, pool.submit(finish, sc, r), r))

        def release_oldest():
            at, nbytes, fut, r = done.popleft()
            chunk = fut.result()
            _merge(report, r)
            return at, nbytes, None, chunk

        while True:
            try:
                at, w = next(words)
            except StopIteration:
                break
            except DecodeError:  # a partial last word (strict): earlier chunks first
                while scans:
                    settle_oldest()
                while done:
                    yield release_oldest()
                raise
            r = DecodeReport()
            fut = pool.submit(scan, w, predicted.copy(), r, at)
            predicted = codec.carry(w, predicted)
            scans.append((at, w.nbytes, fut, r, predicted))
            if len(scans) > workers:
                settle_oldest()
            while len(done) > workers:
                yield release_oldest()
        while scans:
            settle_oldest()
        while done:
            yield release_oldest()


def _counts(sc: ScannedChunk) -> tuple[int, int]:
    """Event words that keep their events, and triggers, of a scanned chunk."""
    n = int(sc.epos.size) if sc.mask is None else int(np.count_nonzero(sc.mask))
    return n, int(sc.triggers[0].size)


def _decode_chunks_jit(
    path, codec, words, state, report, width, height, strict, expand, snapshots
) -> Iterator[tuple]:
    """`decode_chunks` with the compiled kernels (serial)."""
    from . import _decode_jit

    for at, w in words:
        before = state.copy() if snapshots else None
        try:
            if expand:
                out = _decode_jit.decode_words(
                    codec.key, w, state, width=width, height=height, report=report,
                    strict=strict, byte_offset=at,
                )  # fmt: skip
            else:
                out = _decode_jit.count_words(
                    codec.key, w, state, report=report, strict=strict, byte_offset=at
                )
        except DecodeError as err:
            raise DecodeError(f"{path}: {err}") from None
        yield at, w.nbytes, before, out


def _concat(parts: list[DecodedChunk]) -> DecodedChunk:
    """The chunks of a range joined into one."""
    if not parts:
        return DecodedChunk.empty()
    if len(parts) == 1:
        return parts[0]
    return DecodedChunk(*(np.concatenate(cols) for cols in zip(*parts)))


@contextlib.contextmanager
def _mapped(path: Path, offset: int, stop: int) -> Iterator[memoryview]:
    """The bytes `[offset, stop)` of a file, memory-mapped (read in, where mapping is
    not possible): no copy and no fresh pages to fault in."""
    with open(path, "rb") as f:
        size = max(0, min(stop, os.fstat(f.fileno()).st_size) - offset)
        if size == 0:
            yield memoryview(b"")
            return
        try:
            mm = mmap.mmap(f.fileno(), offset + size, access=mmap.ACCESS_READ)
        except (OSError, ValueError):
            f.seek(offset)
            yield memoryview(f.read(size))
            return
    view = memoryview(mm)[offset:]
    try:
        yield view
    finally:
        try:
            view.release()
            mm.close()
        except BufferError:  # arrays on it still referenced (an error's traceback)
            pass  # the map is closed when they are collected


def decode_range(
    path: Path,
    codec: Codec,
    offset: int,
    stop: int,
    state,
    report: DecodeReport,
    *,
    chunk_bytes: int,
    width: int,
    height: int,
    strict: bool = False,
    workers: int = 1,
) -> DecodedChunk:
    """All events of `path[offset:stop]` as one chunk (arguments as `decode_chunks`).

    With the compiled kernels the range is read and decoded in one call (arrays sized
    once, no concatenation); results, report and strict-mode errors are those of
    decoding it in chunks of `chunk_bytes`.
    """
    if not _numba.use_numba():
        chunks = decode_chunks(
            path, codec, offset, stop, state, report, chunk_bytes=chunk_bytes,
            width=width, height=height, strict=strict, workers=workers,
        )  # fmt: skip
        return _concat([c for *_, c in chunks])
    from . import _decode_jit

    wb = codec.word_bytes
    error = None
    with _mapped(path, offset, stop) as data:
        partial = len(data) % wb
        try:
            out = _decode_jit.decode_all(
                codec.key, np.frombuffer(data, codec.dtype, count=len(data) // wb),
                state, width=width, height=height, report=report, strict=strict,
                byte_offset=offset, chunk_bytes=chunk_bytes,
            )  # fmt: skip
        except DecodeError as err:  # raised below, once the map is released
            error = str(err)
    if error is not None:
        raise DecodeError(f"{path}: {error}")
    if partial:
        if strict:
            raise DecodeError(
                f"{path}: file ends with {partial} byte(s) of a partial "
                f"{8 * wb}-bit word (strict mode)"
            )
        report.trailing_bytes += partial
    return out
