"""Vectorised decoding of Prophesee EVT 3.0 words, one chunk at a time.

EVT 3.0 is a stateful stream of 16-bit little-endian words, type in bits 15..12:

| type | name          | payload (bits 11..0)                                        |
|------|---------------|-------------------------------------------------------------|
| 0x0  | EVT_ADDR_Y    | bit 11 system type (master/slave), bits 10..0 row `y`       |
| 0x2  | EVT_ADDR_X    | bit 11 polarity, bits 10..0 column `x`: one CD event        |
| 0x3  | VECT_BASE_X   | bit 11 polarity, bits 10..0 base column for vector words     |
| 0x4  | VECT_12       | 12-bit mask: events at base+i for set bits i; base += 12     |
| 0x5  | VECT_8        | bits 7..0 mask: events at base+i; base += 8                  |
| 0x6  | EVT_TIME_LOW  | low 12 bits of the 24-bit time (µs)                         |
| 0x7  | CONTINUED_4   | 4 bits of extra data for OTHERS (skipped)                    |
| 0x8  | EVT_TIME_HIGH | high 12 bits of the 24-bit time; resets the low part to 0    |
| 0xA  | EXT_TRIGGER   | bits 11..8 channel id, bit 0 edge value (1 rising)           |
| 0xE  | OTHERS        | sub-type of a non-CD event (skipped)                         |
| 0xF  | CONTINUED_12  | 12 bits of extra data for OTHERS (skipped)                   |

Types 0x1, 0x9, 0xB, 0xC and 0xD are reserved ("unknown" below).

**Time.** An event's time is `epoch·2^24 + TIME_HIGH·2^12 + TIME_LOW` from the latest
time words; a TIME_HIGH resets the low part to 0. A TIME_HIGH that falls by more than
half its range (2048 steps, 8.39 s) is a 24-bit wrap (`epoch += 1`); a smaller fall is a
glitch, not a wrap. TIME_LOW never wraps: real sensors (the bundled Gen4.1 recording)
let it step back a few µs within one TIME_HIGH. Output times are made non-decreasing by
a *running maximum over event times* (not over time words: a TIME_LOW that runs ahead and
comes back without events in between changes nothing), applied by `apply_time`; clamped
events are counted in `DecodeReport.time_clamped`. Triggers get their own maximum.

**Vectorisation.** `scan_evt3_words` works per word, with no Python loop: one cumulative
sum over a per-type lookup counts time words, row words and VECT_BASE_X words at once
(three 21-bit fields of an int64), which gives every event word the index of its latest
time, row and vector-base word; vector bases add a cumulative sum of the 12/8-column
increments. Times are relative to the chunk's first epoch (the caller adds the epoch),
so a scan only needs the state that the previous chunk's last words decide —
`carry_evt3_state` predicts it cheaply, which lets chunks be scanned in parallel.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._chunks import (
    POPCOUNT12,
    DecodedChunk,
    ScannedChunk,
    apply_time,
    concat_scanned,
    expand_events,
)
from ._report import DecodeError, DecodeReport

__all__ = [
    "Evt3State",
    "scan_evt3_words",
    "carry_evt3_state",
    "decode_evt3_words",
    "POPCOUNT12",
]

ADDR_Y, ADDR_X, VECT_BASE_X, VECT_12, VECT_8 = 0x0, 0x2, 0x3, 0x4, 0x5
TIME_LOW, CONTINUED_4, TIME_HIGH, EXT_TRIGGER = 0x6, 0x7, 0x8, 0xA
OTHERS, CONTINUED_12 = 0xE, 0xF
UNKNOWN_TYPES = (0x1, 0x9, 0xB, 0xC, 0xD)
HALF_RANGE_STEPS = 2048  # a TIME_HIGH fall larger than this is a wrap

_FIELD = 21
_FIELD_MASK = (1 << _FIELD) - 1
MAX_SCAN_WORDS = 1 << 20  # < 2**_FIELD: counts fit their fields (and cs int32)
_PACK = np.zeros(16, np.int64)
_PACK[TIME_LOW] = _PACK[TIME_HIGH] = 1
_PACK[ADDR_Y] = 1 << _FIELD
_PACK[VECT_BASE_X] = 1 << (2 * _FIELD)
_UNKNOWN = np.zeros(16, bool)
_UNKNOWN[list(UNKNOWN_TYPES)] = True
_UNKNOWN_BITS = np.uint16(sum(1 << k for k in UNKNOWN_TYPES))
_OTHER_BITS = np.uint16((1 << CONTINUED_4) | (1 << OTHERS) | (1 << CONTINUED_12))


@dataclasses.dataclass
class Evt3State:
    """Decoder state carried from one chunk to the next (-1 = not seen yet).

    `time` is the current time within the current epoch (`TIME_HIGH·2^12 + TIME_LOW`,
    below 2^24); `epoch` counts 24-bit wraps; `last_t` and `last_trig_t` are the running
    maxima of absolute event and trigger times (kept by `apply_time`, not the scan).
    """

    y: int = -1
    base_x: int = -1
    vpol: int = 0
    th: int = -1
    epoch: int = 0
    time: int = -1
    last_t: int = -1
    last_trig_t: int = -1

    def copy(self) -> Evt3State:
        return dataclasses.replace(self)


def _fail(what: str, offset: int) -> DecodeError:
    return DecodeError(f"EVT 3.0 stream: {what} at byte {offset} (strict mode)")


def _time_values(w, t8, tpos, state: Evt3State, report: DecodeReport):
    """Time after each time word (TIME_LOW/TIME_HIGH), -1 where still unknown, and the
    number of wraps; times count epochs from the chunk start (its epoch is 0)."""
    tv = np.take(w, tpos).astype(np.int64) & 0xFFF
    is_th = np.take(t8, tpos) == TIME_HIGH
    thi = np.flatnonzero(is_th)
    th_before = -1 if state.th < 0 else state.th << 12
    ext = np.empty(thi.size + 1, np.int64)
    ext[0] = th_before
    if thi.size:
        thv = tv[thi]
        prev = np.empty_like(thv)
        prev[0] = state.th
        prev[1:] = thv[:-1]
        fall = prev - thv
        known = prev >= 0
        wrap = known & (fall > HALF_RANGE_STEPS)
        report.time_glitches += int(np.count_nonzero(known & (fall > 0) & ~wrap))
        nwrap = np.cumsum(wrap)
        wraps = int(nwrap[-1])
        ext[1:] = (nwrap << 24) | (thv << 12)  # relative to the chunk's first epoch
        state.th = int(thv[-1])
    else:
        wraps = 0
    base = np.take(ext, np.cumsum(is_th))
    values = np.where(is_th, base, base + tv)
    values[base < 0] = -1
    return values, wraps


def scan_evt3_words(
    w: np.ndarray,
    state: Evt3State,
    *,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
) -> ScannedChunk:
    """Stage 1 of decoding a chunk: per-word states, updating `state` and `report`.

    **Arguments:**

    - `w`: the chunk's words, shape `(n,)`, `uint16` (already little-endian).
    - `state`: decoder state at the chunk start; updated to the state at its end.
    - `report`: counters, updated in place.
    - `strict`: raise `DecodeError` (a `ValueError`) on the first defect.
    - `byte_offset`: file offset of `w[0]`, for messages.

    **Returns:** a `ScannedChunk` (per event word: column base, polarity, row, time).
    """
    if w.size > MAX_SCAN_WORDS:  # the packed counters below have 21-bit fields
        parts = [
            scan_evt3_words(
                w[i : i + MAX_SCAN_WORDS],
                state,
                report=report,
                strict=strict,
                byte_offset=byte_offset + 2 * i,
            )
            for i in range(0, w.size, MAX_SCAN_WORDS)
        ]
        return concat_scanned(parts, word_bytes=2, epoch_bits=24)
    n = int(w.size)
    report.words += n
    t8 = (w >> 12).astype(np.uint8)
    n_unknown = int(np.count_nonzero((_UNKNOWN_BITS >> t8) & 1)) if n else 0
    defects = []  # strict mode: (word index, what), the earliest is raised
    if n_unknown:
        if strict:
            first = int(np.flatnonzero(_UNKNOWN[t8])[0])
            defects.append((first, f"reserved word type {int(t8[first]):#x}"))
        report.unknown_words += n_unknown
    if n:
        report.other_words += int(np.count_nonzero((_OTHER_BITS >> t8) & 1))
    start = state.copy()
    # One cumulative sum counts time words, row words and VECT_BASE_X words at once
    # (three 21-bit fields): at every word, the index of the latest word of each kind.
    counts = np.cumsum(np.take(_PACK, t8))

    # --- time words ---
    is_time = (t8 == TIME_LOW) | (t8 == TIME_HIGH)
    tpos = np.flatnonzero(is_time)
    time_ext = np.empty(tpos.size + 1, np.int64)
    time_ext[0] = state.time
    wraps = 0
    if tpos.size:
        time_ext[1:], wraps = _time_values(w, t8, tpos, state, report)
    report.time_wraps += wraps
    state.epoch += wraps
    last = int(time_ext[-1])
    state.time = last - (wraps << 24) if last >= 0 else -1

    # --- rows ---
    ypos = np.flatnonzero(t8 == ADDR_Y)
    y_ext = np.empty(ypos.size + 1, np.uint16)
    y_ext[0] = max(state.y, 0)
    if ypos.size:
        yw = np.take(w, ypos)
        report.system_type_rows += int(np.count_nonzero(yw & 0x800))
        y_ext[1:] = yw & 0x7FF
        state.y = int(y_ext[-1])

    # --- event words, and vector bases ---
    rpos = np.flatnonzero((t8 - np.uint8(ADDR_X)) <= VECT_8 - ADDR_X)
    rt = np.take(t8, rpos)
    rw = np.take(w, rpos)
    is_vb = rt == VECT_BASE_X
    vbi = np.flatnonzero(is_vb)
    mask = None
    evi = np.flatnonzero(~is_vb) if vbi.size else None
    epos = rpos if evi is None else np.take(rpos, evi)
    ew = rw if evi is None else np.take(rw, evi)
    packed = np.take(counts, epos)
    base = ew & 0x7FF
    pol = ((ew >> 11) & 1).astype(np.uint8)
    vr = np.flatnonzero(rt >= VECT_BASE_X)  # VECT_BASE_X and vector words
    if vr.size:
        # Base column of a vector word: its VECT_BASE_X column plus the 12/8-column
        # increments of the vector words in between (`cs`, a running sum over the
        # vector-related words only).
        vt = np.take(rt, vr)
        incr = (vt == VECT_12) * np.uint8(12) + (vt == VECT_8) * np.uint8(8)
        cs = np.cumsum(incr, dtype=np.int32)
        is_vb_v = vt == VECT_BASE_X
        vbw = np.take(rw, vbi)
        off_ext = np.empty(vbi.size + 1, np.int32)
        off_ext[0] = max(state.base_x, 0)
        off_ext[1:] = (vbw & 0x7FF) - np.take(cs, np.flatnonzero(is_vb_v))
        pol_ext = np.empty(vbi.size + 1, np.uint8)
        pol_ext[0] = state.vpol
        pol_ext[1:] = (vbw >> 11) & 1
        if state.base_x >= 0 or vbi.size:
            state.base_x = int(off_ext[-1]) + int(cs[-1])
            state.vpol = int(pol_ext[-1])
        vv = np.flatnonzero(~is_vb_v)  # the vector words, among `vr`
        if vv.size:
            et = rt if evi is None else np.take(rt, evi)
            vi = np.flatnonzero(et != ADDR_X)  # the same words, among event words
            g = np.take(packed, vi) >> (2 * _FIELD)  # VECT_BASE_X words before each
            vbase = np.take(off_ext, g) + np.take(cs, vv) - np.take(incr, vv)
            # A long run of vector words is capped so uint16 columns cannot wrap.
            base[vi] = np.minimum(vbase, 0xFFF0)
            pol[vi] = np.take(pol_ext, g)
            vw = np.take(ew, vi)
            mask = np.ones(epos.size, np.uint16)
            mask[vi] = vw & (np.uint16(0xFFF) - (vw >> 12 == VECT_8) * np.uint16(0xF00))
            if start.base_x < 0:
                orphan = vi[g == 0]
                lost = int(POPCOUNT12[mask[orphan]].sum())
                if strict and lost:
                    first = int(epos[orphan[np.flatnonzero(mask[orphan])[0]]])
                    defects.append((first, "vector word before any VECT_BASE_X"))
                report.events_without_row += lost
                mask[orphan] = 0

    t_w = np.take(time_ext, packed & _FIELD_MASK)
    yidx = (packed >> _FIELD) & _FIELD_MASK
    y_w = np.take(y_ext, yidx)

    # Event words before the first TIME_HIGH or the first EVT_ADDR_Y are unusable.
    if (start.time < 0 or start.y < 0) and epos.size:
        no_t = t_w < 0
        no_y = (yidx == 0) & (start.y < 0) & ~no_t
        if no_t.any() or no_y.any():
            if mask is None:
                mask = np.ones(epos.size, np.uint16)
            lost_t = int(POPCOUNT12[mask[no_t]].sum())
            lost_y = int(POPCOUNT12[mask[no_y]].sum())
            if strict and (lost_t or lost_y):
                k = int(np.flatnonzero((no_t | no_y) & (mask > 0))[0])
                what = "TIME_HIGH" if no_t[k] else "EVT_ADDR_Y"
                defects.append((int(epos[k]), f"CD event before the first {what}"))
            report.events_before_time += lost_t
            report.events_without_row += lost_y
            mask[no_t | no_y] = 0

    triggers = _triggers(w, t8, counts, time_ext, report, strict, defects)
    if defects:
        first, what = min(defects)
        raise _fail(what, byte_offset + 2 * first)
    return ScannedChunk(base, pol, y_w, t_w, mask, epos, byte_offset, triggers, wraps)


def carry_evt3_state(w: np.ndarray, state: Evt3State) -> Evt3State:
    """The state `scan_evt3_words` leaves after chunk `w`, predicted cheaply.

    Row, vector base and polarity, TIME_HIGH and time only depend on the last words of
    each kind, so they are read from the chunk's tail (the whole chunk is searched only
    when a kind is missing there). `epoch`, `last_t` and `last_trig_t` are left as they
    are: they are settled in chunk order by `apply_time`. This lets the next chunk's
    scan start before this one's has finished.

    **Arguments:**

    - `w`: the chunk's words, `uint16`.
    - `state`: the state at the chunk start.

    **Returns:** a new `Evt3State`.
    """
    out = state.copy()
    n = int(w.size)
    if n == 0:
        return out
    lo = max(0, n - 4096)
    t8_tail = (w[lo:] >> 12).astype(np.uint8)
    head: list = []  # types of w[:lo], computed only if needed

    def last(*kinds: int) -> int:
        """Index of the last word of one of `kinds`, or -1."""
        hit = np.flatnonzero(np.isin(t8_tail, kinds))
        if hit.size:
            return lo + int(hit[-1])
        if lo == 0:
            return -1
        if not head:
            head.append((w[:lo] >> 12).astype(np.uint8))
        hit = np.flatnonzero(np.isin(head[0], kinds))
        return int(hit[-1]) if hit.size else -1

    def increments(after: int) -> int:
        t8 = (w[after:] >> 12).astype(np.uint8)
        return 12 * int(np.count_nonzero(t8 == VECT_12)) + 8 * int(
            np.count_nonzero(t8 == VECT_8)
        )

    iy = last(ADDR_Y)
    if iy >= 0:
        out.y = int(w[iy]) & 0x7FF
    ih = last(TIME_HIGH)
    if ih >= 0:
        out.th = int(w[ih]) & 0xFFF
    it = last(TIME_LOW, TIME_HIGH)
    if it == ih >= 0:
        out.time = out.th << 12
    elif it >= 0:
        th = out.th  # the TIME_HIGH before this TIME_LOW (here or in an earlier chunk)
        out.time = -1 if th < 0 else (th << 12) + (int(w[it]) & 0xFFF)
    ib = last(VECT_BASE_X)
    if ib >= 0:
        out.base_x = (int(w[ib]) & 0x7FF) + increments(ib + 1)
        out.vpol = (int(w[ib]) >> 11) & 1
    elif state.base_x >= 0:
        out.base_x = state.base_x + increments(0)
    return out


def decode_evt3_words(
    w: np.ndarray,
    state: Evt3State,
    *,
    width: int,
    height: int,
    report: DecodeReport,
    strict: bool = False,
    byte_offset: int = 0,
) -> DecodedChunk:
    """Decode one chunk of EVT 3.0 words (`scan_evt3_words`, `apply_time`,
    `expand_events`), updating `state` and `report`.

    **Arguments:** as for those two functions.

    **Returns:** a `DecodedChunk` of CD events in file order and trigger events.
    """
    epoch = state.epoch
    sc = scan_evt3_words(
        w, state, report=report, strict=strict, byte_offset=byte_offset
    )
    sc = apply_time(sc, epoch << 24, state, report)
    return expand_events(
        sc, width=width, height=height, report=report, strict=strict, fmt="EVT 3.0"
    )


def _triggers(w, t8, counts, time_ext, report, strict, defects):
    gpos = np.flatnonzero(t8 == EXT_TRIGGER)
    if not gpos.size:
        return np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.uint8)
    gw = np.take(w, gpos)
    gt = np.take(time_ext, np.take(counts, gpos) & _FIELD_MASK)
    ok = gt >= 0
    if not ok.all():
        if strict:
            defects.append(
                (
                    int(gpos[np.flatnonzero(~ok)[0]]),
                    "trigger before the first TIME_HIGH",
                )
            )
        report.events_before_time += int((~ok).sum())
        gw, gt = gw[ok], gt[ok]
    report.triggers += int(gt.size)
    return gt, (gw & 1).astype(np.uint8), ((gw >> 8) & 0xF).astype(np.uint8)
