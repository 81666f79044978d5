"""Compiled (numba) EVT 3.0 and EVT 2.0 decoders: one sequential pass per chunk.

Same semantics as the vectorised reference (`_evt3_decode`, `_evt2`, `_chunks`), word by
word: the kernel carries the decoder state (row, vector base and polarity, TIME_HIGH,
time within the epoch, wrap epoch, running maxima of event and trigger times) in and
out of each call, so chunked decoding works exactly as in the NumPy path. Per event
word it applies, in this order, the checks of the reference: a vector word before any
VECT_BASE_X (its events lost, `events_without_row`), an event before the first TIME_HIGH
(`events_before_time`) or the first EVT_ADDR_Y (`events_without_row`); then the running
maximum (`time_clamped`, `max_step_back_us`; events outside the geometry count in it,
as in `apply_time`), then the geometry (`out_of_geometry`). A TIME_LOW never wraps; a
TIME_HIGH fall of more than half the range is a wrap, a smaller one a glitch.

Strict mode: the kernel records the first *scan* defect (reserved word, lost event or
trigger) and the first event outside the geometry; like the reference, which checks the
geometry only after scanning a whole chunk, the scan defect wins when it lies in the
same or an earlier chunk (`chunk_bytes` decides), so the same `DecodeError` is raised.

Output arrays are sized by a cheap, branch-free first pass (the events of every word)
and filled without branches per bit (12 slots written, the cursor advanced by each bit),
hence 12 spare slots. The kernels are in `_decode_kernels`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._base import readonly
from ._chunks import DecodedChunk
from ._decode_kernels import (
    C_BEFORE,
    C_CLAMPED,
    C_EVENTS,
    C_GLITCHES,
    C_MAXSTEP,
    C_NOROW,
    C_OOG,
    C_OTHER,
    C_SYSTEM,
    C_TRIGGERS,
    C_UNKNOWN,
    C_VALID,
    C_WRAPS,
    bound2,
    bound3,
    evt2,
    evt3,
)
from ._evt2 import Evt2State
from ._evt3_decode import Evt3State
from ._report import DecodeError, DecodeReport

__all__ = ["decode_words", "decode_all", "count_words"]

_SLACK = 12  # spare output slots (see `_decode_kernels`)

_REPORT = {
    "events": C_EVENTS, "triggers": C_TRIGGERS, "time_wraps": C_WRAPS,
    "time_glitches": C_GLITCHES, "time_clamped": C_CLAMPED, "other_words": C_OTHER,
    "system_type_rows": C_SYSTEM, "unknown_words": C_UNKNOWN,
    "out_of_geometry": C_OOG, "events_before_time": C_BEFORE,
    "events_without_row": C_NOROW,
}  # fmt: skip
# Scan defect codes (slot 1 of `defect`; slot 2 holds the word type of code 1).
_WHAT = {
    1: "reserved word type {:#x}",
    2: "vector word before any VECT_BASE_X",
    3: "CD event before the first TIME_HIGH",
    4: "CD event before the first EVT_ADDR_Y",
    5: "trigger before the first TIME_HIGH",
}


@dataclasses.dataclass(frozen=True)
class _Format:
    name: str
    word_bytes: int
    dtype: type
    state: type
    bound: object
    kernel: object


_FORMATS = {
    "evt3": _Format("EVT 3.0", 2, np.uint16, Evt3State, bound3, evt3),
    "evt2": _Format("EVT 2.0", 4, np.uint32, Evt2State, bound2, evt2),
}


def _columns(ne: int, ng: int) -> tuple:
    """Empty output columns: x, y, p, t for `ne` events, t, p, id for `ng` triggers."""
    cd = (np.uint16, np.uint16, np.uint8, np.int64)
    return tuple(np.empty(ne, d) for d in cd) + tuple(
        np.empty(ng, d) for d in (np.int64, np.uint8, np.uint8)
    )


def _run(fmt: _Format, w, state, report: DecodeReport, width, height, emit: bool):
    """One kernel call: updates `state` and `report`; returns the chunk (or `None`
    when not `emit`), the `defect` record and the count of valid event words."""
    w = readonly(w, fmt.dtype)
    st = np.array(dataclasses.astuple(state), np.int64)
    cnt = np.zeros(13, np.int64)
    defect = np.full(6, -1, np.int64)
    ne, ng = fmt.bound(w) if emit else (0, 0)
    cols = _columns(ne + _SLACK if emit else 0, ng)
    n, ng = fmt.kernel(w, st, cnt, defect, int(width), int(height), emit, *cols)
    for f, v in zip(dataclasses.fields(state), st.tolist()):
        setattr(state, f.name, v)
    report.words += int(w.size)
    for name, slot in _REPORT.items():
        setattr(report, name, getattr(report, name) + int(cnt[slot]))
    report.max_step_back_us = max(report.max_step_back_us, int(cnt[C_MAXSTEP]))
    chunk = None
    if emit:  # views of the buffers, unless many events were dropped
        cd = [a[:n] if 4 * (ne - n) <= ne else a[:n].copy() for a in cols[:4]]
        chunk = DecodedChunk(*cd, *(a[:ng] for a in cols[4:]))
    return chunk, defect, int(cnt[C_VALID])


def _scan_error(fmt: _Format, defect, byte_offset: int) -> DecodeError:
    what = _WHAT[int(defect[1])].format(int(defect[2]))
    at = byte_offset + fmt.word_bytes * int(defect[0])
    return DecodeError(f"{fmt.name} stream: {what} at byte {at} (strict mode)")


def _geometry_error(fmt: _Format, defect, byte_offset, width, height) -> DecodeError:
    at = byte_offset + fmt.word_bytes * int(defect[3])
    return DecodeError(
        f"{fmt.name} stream: event ({int(defect[4])}, {int(defect[5])}) outside the "
        f"{width}x{height} geometry at byte {at} (strict mode)"
    )


def decode_words(
    key: str,
    w: np.ndarray,
    state,
    *,
    width: int,
    height: int,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
) -> DecodedChunk:
    """Decode one chunk (compiled); as `decode_evt3_words` / `decode_evt2_words`.

    **Arguments:**

    - `key`: `"evt3"` or `"evt2"`.
    - `w`: the chunk's words (`uint16` / `uint32`, little-endian already).
    - `state`: `Evt3State` / `Evt2State` at the chunk start; updated.
    - `width`, `height`, `report`, `strict`, `byte_offset`: as for the reference.

    **Returns:** the chunk's `DecodedChunk`.
    """
    fmt = _FORMATS[key]
    chunk, defect, _ = _run(fmt, w, state, report, width, height, True)
    if strict and defect[0] >= 0:  # a scan defect outranks the geometry (reference)
        raise _scan_error(fmt, defect, byte_offset)
    if strict and defect[3] >= 0:
        raise _geometry_error(fmt, defect, byte_offset, width, height)
    return chunk


def count_words(
    key: str,
    w: np.ndarray,
    state,
    *,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
) -> tuple[int, int]:
    """Advance `state` over one chunk without producing events (the window index).

    Geometry is not checked (the reference does not expand events here either).

    **Returns:** `(event words that keep their events, triggers)`.
    """
    fmt = _FORMATS[key]
    n_triggers = report.triggers
    _, defect, valid = _run(fmt, w, state, report, 1 << 16, 1 << 16, False)
    if strict and defect[0] >= 0:
        raise _scan_error(fmt, defect, byte_offset)
    return valid, report.triggers - n_triggers


def decode_all(
    key: str,
    w: np.ndarray,
    state,
    *,
    width: int,
    height: int,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
    chunk_bytes: int,
) -> DecodedChunk:
    """Decode a whole byte range in one call, as if in chunks of `chunk_bytes` read
    from `byte_offset` (which only decides which strict-mode error comes first).

    **Returns:** the range's `DecodedChunk`.
    """
    fmt = _FORMATS[key]
    chunk, defect, _ = _run(fmt, w, state, report, width, height, True)
    if strict and (defect[0] >= 0 or defect[3] >= 0):
        wb = fmt.word_bytes

        def chunk_of(j: int) -> int:  # the chunk in which word j is completed
            return (wb * j + wb - 1) // chunk_bytes

        if defect[0] >= 0 and (
            defect[3] < 0 or chunk_of(int(defect[0])) <= chunk_of(int(defect[3]))
        ):
            raise _scan_error(fmt, defect, byte_offset)
        raise _geometry_error(fmt, defect, byte_offset, width, height)
    return chunk
