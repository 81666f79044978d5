"""Vectorised decoding of Prophesee EVT 2.0 words (read only).

EVT 2.0 is a stream of 32-bit little-endian words, type in bits 31..28:

| type | name          | payload                                                       |
|------|---------------|---------------------------------------------------------------|
| 0x0  | CD_OFF        | bits 27..22 time low (6 bits), 21..11 `x`, 10..0 `y`; p=0     |
| 0x1  | CD_ON         | same layout; p = 1                                            |
| 0x8  | EVT_TIME_HIGH | bits 27..0: time high (28 bits); time = high·64 + low (µs)    |
| 0xA  | EXT_TRIGGER   | bits 27..22 time low, 12..8 channel id, bit 0 edge value      |
| 0xE  | OTHERS        | skipped                                                       |
| 0xF  | CONTINUED     | skipped                                                       |

Other types are reserved ("unknown"). The 34-bit time base wraps every 2^34 µs (4.77 h):
a TIME_HIGH that falls by more than half its range is a wrap; a smaller fall is a
glitch. As for EVT 3.0, output times are made non-decreasing by a running maximum
(counted in the report), events before the first TIME_HIGH are skipped, and policy is
lenient unless `strict=True`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._chunks import DecodedChunk, ScannedChunk, apply_time, expand_events
from ._report import DecodeError, DecodeReport

__all__ = ["Evt2State", "scan_evt2_words", "carry_evt2_state", "decode_evt2_words"]

CD_OFF, CD_ON, TIME_HIGH, EXT_TRIGGER, OTHERS, CONTINUED = 0x0, 0x1, 0x8, 0xA, 0xE, 0xF
_UNKNOWN = np.ones(16, bool)
_UNKNOWN[[CD_OFF, CD_ON, TIME_HIGH, EXT_TRIGGER, OTHERS, CONTINUED]] = False
_UNKNOWN_BITS = np.uint16(sum(1 << k for k in range(16) if _UNKNOWN[k]))
HALF_RANGE = 1 << 27


@dataclasses.dataclass
class Evt2State:
    """Decoder state carried from one chunk to the next (-1 = not seen yet)."""

    th: int = -1
    epoch: int = 0
    last_t: int = -1
    last_trig_t: int = -1

    def copy(self) -> Evt2State:
        return dataclasses.replace(self)


def _fail(what: str, offset: int) -> DecodeError:
    return DecodeError(f"EVT 2.0 stream: {what} at byte {offset} (strict mode)")


def scan_evt2_words(
    w: np.ndarray,
    state: Evt2State,
    *,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
) -> ScannedChunk:
    """Stage 1 of decoding a chunk of EVT 2.0 words, updating `state` and `report`.

    **Arguments:**

    - `w`: the chunk's words, shape `(n,)`, `uint32` (already little-endian).
    - `state`, `report`, `strict`, `byte_offset`: as for `scan_evt3_words`.

    **Returns:** a `ScannedChunk` (one event per CD word, so `mask` is `None`).
    """
    n = int(w.size)
    report.words += n
    t8 = (w >> 28).astype(np.uint8)
    n_unknown = int(np.count_nonzero((_UNKNOWN_BITS >> t8) & 1)) if n else 0
    unknown = None
    if n_unknown:
        if strict:
            first = int(np.flatnonzero(_UNKNOWN[t8])[0])
            unknown = (first, f"reserved word type {int(t8[first]):#x}")
        report.unknown_words += n_unknown
    if n:
        report.other_words += int(np.count_nonzero(t8 >= OTHERS))

    # Time high of each piece between TIME_HIGH words, extended across wraps.
    is_th = t8 == TIME_HIGH
    hpos = np.flatnonzero(is_th)
    ext = np.empty(hpos.size + 1, np.int64)
    ext[0] = -1 if state.th < 0 else state.th << 6
    wraps = 0
    if hpos.size:
        thv = (np.take(w, hpos) & 0x0FFFFFFF).astype(np.int64)
        prev = np.empty_like(thv)
        prev[0] = state.th
        prev[1:] = thv[:-1]
        fall = prev - thv
        known = prev >= 0
        wrap = known & (fall > HALF_RANGE)
        report.time_glitches += int(np.count_nonzero(known & (fall > 0) & ~wrap))
        nwrap = np.cumsum(wrap)
        wraps = int(nwrap[-1])
        report.time_wraps += wraps
        ext[1:] = (nwrap << 34) | (thv << 6)  # relative to the chunk's first epoch
        state.th = int(thv[-1])
        state.epoch += wraps
    hcum = np.cumsum(is_th, dtype=np.int64) if hpos.size else None

    defects = []  # strict mode: (word index, what), the earliest is raised

    def timed(pos: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
        """Times of the words at `pos` (time low in bits 27..22); invalid → dropped."""
        high = (
            np.take(ext, np.take(hcum, pos))
            if hcum is not None
            else (np.full(pos.size, ext[0], np.int64))
        )
        ok = high >= 0
        if not ok.all():
            if strict:
                first = int(pos[np.flatnonzero(~ok)[0]])
                defects.append((first, f"{what} before the first TIME_HIGH"))
            report.events_before_time += int((~ok).sum())
            pos, high = pos[ok], high[ok]
        return pos, high + ((np.take(w, pos) >> 22) & 0x3F)

    # Triggers.
    gpos = np.flatnonzero(t8 == EXT_TRIGGER)
    if gpos.size:
        gpos, gt = timed(gpos, "trigger")
        gw = np.take(w, gpos)
        trig = gt, (gw & 1).astype(np.uint8), ((gw >> 8) & 0x1F).astype(np.uint8)
    else:
        trig = np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.uint8)
    report.triggers += int(trig[0].size)

    # CD events.
    epos, t = timed(np.flatnonzero(t8 <= CD_ON), "CD event")
    if unknown is not None:
        defects.append(unknown)
    if defects:
        first, what = min(defects)
        raise _fail(what, byte_offset + 4 * first)
    ew = np.take(w, epos)
    x = ((ew >> 11) & 0x7FF).astype(np.uint16)
    y = (ew & 0x7FF).astype(np.uint16)
    p = np.take(t8, epos)
    return ScannedChunk(x, p, y, t, None, epos, byte_offset, trig, wraps)


def carry_evt2_state(w: np.ndarray, state: Evt2State) -> Evt2State:
    """The state `scan_evt2_words` leaves after chunk `w` (its last TIME_HIGH), cheaply;
    `epoch`, `last_t` and `last_trig_t` are settled by `apply_time` (see
    `carry_evt3_state`).

    **Arguments:**

    - `w`: the chunk's words, `uint32`; `state`: the state at its start.

    **Returns:** a new `Evt2State`.
    """
    out = state.copy()
    for lo in (max(0, w.size - 4096), 0):
        hit = np.flatnonzero((w[lo:] >> 28) == TIME_HIGH)
        if hit.size:
            out.th = int(w[lo + int(hit[-1])]) & 0x0FFFFFFF
            break
        if lo == 0:
            break
    return out


def decode_evt2_words(
    w: np.ndarray,
    state: Evt2State,
    *,
    width: int,
    height: int,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
) -> DecodedChunk:
    """Decode one chunk of EVT 2.0 words (`scan_evt2_words`, `apply_time`,
    `expand_events`), updating `state` and `report`.

    **Arguments:** as for those two functions.

    **Returns:** a `DecodedChunk` of CD events in file order and trigger events.
    """
    epoch = state.epoch
    sc = scan_evt2_words(
        w, state, report=report, strict=strict, byte_offset=byte_offset
    )
    sc = apply_time(sc, epoch << 34, state, report)
    return expand_events(
        sc,
        width=width,
        height=height,
        report=report,
        strict=strict,
        word_bytes=4,
        fmt="EVT 2.0",
    )
