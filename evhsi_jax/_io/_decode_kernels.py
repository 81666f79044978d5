"""The numba kernels of `_decode_jit`: EVT 3.0 and EVT 2.0, one pass over the words.

`evt3(w, st, cnt, defect, width, height, emit, x, y, p, t, gt, gp, gid)` (and `evt2`,
the same arguments) decodes the words `w` from the state `st` (int64: row, vector base,
vector polarity, TIME_HIGH, epoch, time, last event time, last trigger time; EVT 2.0:
TIME_HIGH, epoch, last event time, last trigger time; -1 = not seen), which it leaves
as the state after `w`. Counts are added to `cnt` (slots `C_*`), the first scan defect
(word index, code, info) and the first event outside `width` x `height` (word index,
column, row) are recorded in `defect` (-1: none). With `emit`, CD events go to `x, y,
p, t` and triggers to `gt, gp, gid` (sized by `bound3` / `bound2`, plus 12 spare
slots: a vector word writes 12 slots and advances by the bits set). Returns the number
of events and of triggers. The per-word rules are those of the NumPy reference; see
`_decode_jit`.

Kernels are marked `no_type_check` so that the jaxtyping import hook of the test suite
leaves them to numba.
"""

from __future__ import annotations

from typing import no_type_check

import numpy as np

from .._base import njit

__all__ = ["bound3", "bound2", "evt3", "evt2"]

_POP = np.array([bin(i).count("1") for i in range(1 << 12)], np.int64)

# Counter slots (kernel side); `valid` = event words that kept their events (the index).
(C_EVENTS, C_TRIGGERS, C_WRAPS, C_GLITCHES, C_CLAMPED, C_MAXSTEP, C_OTHER, C_SYSTEM,
 C_UNKNOWN, C_OOG, C_BEFORE, C_NOROW, C_VALID) = range(13)  # fmt: skip


@njit
@no_type_check
def bound3(w):
    """Events and trigger words in EVT 3.0 words `w` (sizes the outputs)."""
    ne = 0
    ng = 0
    for i in range(w.size):  # branch-free (SWAR popcount of the vector masks)
        v = np.int64(w[i])
        k = v >> 12
        m = v & ((0xFFF if k == 4 else 0) | (0xFF if k == 5 else 0))
        c = m - ((m >> 1) & 0x555)
        c = (c & 0x333) + ((c >> 2) & 0x333)
        c = (c + (c >> 4)) & 0x0F0F
        ne += ((c + (c >> 8)) & 0x1F) + (k == 2)
        ng += k == 0xA
    return ne, ng


@njit
@no_type_check
def bound2(w):
    """CD and trigger words in EVT 2.0 words `w`."""
    ne = 0
    ng = 0
    for i in range(w.size):
        k = w[i] >> 28
        ne += k <= 1
        ng += k == 0xA
    return ne, ng


@njit(inline=True)
@no_type_check
def _note(defect, i, code, info):
    """Record the first scan defect (word index, code, info)."""
    if defect[0] < 0:
        defect[0], defect[1], defect[2] = i, code, info


@njit(inline=True)
@no_type_check
def _outside(defect, i, col, row):
    """Record the first event outside the geometry (word index, column, row)."""
    if defect[3] < 0:
        defect[3], defect[4], defect[5] = i, col, row


@njit(inline=True)
@no_type_check
def _count(cnt, n, ng, valid, wraps, glitches, clamped, maxstep, other, system,
           unknown, oog, before, norow):  # fmt: skip
    """Add a call's counts to `cnt` (kept in locals during the loop: faster)."""
    cnt[C_EVENTS] += n
    cnt[C_TRIGGERS] += ng
    cnt[C_VALID] += valid
    cnt[C_WRAPS] += wraps
    cnt[C_GLITCHES] += glitches
    cnt[C_CLAMPED] += clamped
    cnt[C_MAXSTEP] = max(cnt[C_MAXSTEP], maxstep)
    cnt[C_OTHER] += other
    cnt[C_SYSTEM] += system
    cnt[C_UNKNOWN] += unknown
    cnt[C_OOG] += oog
    cnt[C_BEFORE] += before
    cnt[C_NOROW] += norow


@njit
@no_type_check
def evt3(w, st, cnt, defect, width, height, emit, x, y, p, t, gt, gp, gid):
    cy = st[0]
    bx = st[1]
    vpol = st[2]
    th = st[3]
    epoch = st[4]
    tim = st[5]
    last_t = st[6]
    last_g = st[7]
    tbase = epoch << 24
    n = np.uint64(0)  # unsigned: array stores without negative-index handling
    ng = valid = 0
    wraps = glitches = clamped = maxstep = other = system = unknown = 0
    oog = before = norow = 0
    for i in range(w.size):
        v = np.int64(w[i])
        k = v >> 12
        if k == 2:  # EVT_ADDR_X: one event (the most frequent types first)
            if (tim | cy) < 0:  # no time or no row yet
                before += tim < 0
                norow += tim >= 0
                _note(defect, i, 3 if tim < 0 else 4, 0)
                continue
            te = tbase + tim
            if te < last_t:
                clamped += 1
                maxstep = max(maxstep, last_t - te)
                te = last_t
            else:
                last_t = te
            valid += 1
            col = v & 0x7FF
            if col < width and cy < height:
                if emit:
                    x[n] = col
                    y[n] = cy
                    p[n] = (v >> 11) & 1
                    t[n] = te
                n += np.uint64(1)
            else:
                oog += 1
                _outside(defect, i, col, cy)
            continue
        if k == 0:  # EVT_ADDR_Y
            cy = v & 0x7FF
            system += (v >> 11) & 1
            continue
        if k == 6:  # EVT_TIME_LOW (never wraps)
            if th >= 0:
                tim = (th << 12) | (v & 0xFFF)
            continue
        if k == 4 or k == 5:  # VECT_12, VECT_8: events at base + set bits
            m = v & 0xFFF if k == 4 else v & 0xFF
            if bx < 0:
                norow += _POP[m]
                if m:
                    _note(defect, i, 2, 0)
                continue
            col = min(bx, 0xFFF0)  # capped: uint16 columns never wrap
            bx += 12 if k == 4 else 8
            if m == 0:
                continue
            if (tim | cy) < 0:
                before += _POP[m] if tim < 0 else 0
                norow += _POP[m] if tim >= 0 else 0
                _note(defect, i, 3 if tim < 0 else 4, 0)
                continue
            te = tbase + tim
            if te < last_t:
                clamped += _POP[m]
                maxstep = max(maxstep, last_t - te)
                te = last_t
            else:
                last_t = te
            valid += 1
            if col + 11 < width and cy < height:  # every bit inside the geometry
                if emit:  # 12 slots written, the cursor advanced by each bit
                    for b in range(12):
                        x[n] = col + b
                        y[n] = cy
                        p[n] = vpol
                        t[n] = te
                        n += np.uint64((m >> b) & 1)
                else:
                    n += np.uint64(_POP[m])
                continue
            for b in range(12):
                if (m >> b) & 1:
                    if col + b < width and cy < height:
                        if emit:
                            x[n] = col + b
                            y[n] = cy
                            p[n] = vpol
                            t[n] = te
                        n += np.uint64(1)
                    else:
                        oog += 1
                        _outside(defect, i, col + b, cy)
            continue
        if k == 3:  # VECT_BASE_X
            bx = v & 0x7FF
            vpol = (v >> 11) & 1
        elif k == 8:  # EVT_TIME_HIGH: a fall of more than half the range is a wrap
            nv = v & 0xFFF
            if th >= 0:
                if th - nv > 2048:
                    epoch += 1
                    wraps += 1
                    tbase = epoch << 24
                elif th > nv:
                    glitches += 1
            th = nv
            tim = nv << 12
        elif k == 0xA:  # EXT_TRIGGER
            if tim < 0:
                before += 1
                _note(defect, i, 5, 0)
                continue
            tg = tbase + tim
            if tg < last_g:
                clamped += 1
                maxstep = max(maxstep, last_g - tg)
                tg = last_g
            else:
                last_g = tg
            if emit:
                gt[ng] = tg
                gp[ng] = v & 1
                gid[ng] = (v >> 8) & 0xF
            ng += 1
        elif k == 7 or k >= 0xE:  # CONTINUED_4, OTHERS, CONTINUED_12
            other += 1
        else:  # reserved
            unknown += 1
            _note(defect, i, 1, k)
    st[0] = cy
    st[1] = bx
    st[2] = vpol
    st[3] = th
    st[4] = epoch
    st[5] = tim
    st[6] = last_t
    st[7] = last_g
    events = np.int64(n)
    _count(cnt, events, ng, valid, wraps, glitches, clamped, maxstep, other, system,
           unknown, oog, before, norow)  # fmt: skip
    return events, ng


@njit
@no_type_check
def evt2(w, st, cnt, defect, width, height, emit, x, y, p, t, gt, gp, gid):
    th = st[0]
    epoch = st[1]
    last_t = st[2]
    last_g = st[3]
    tbase = epoch << 34
    n = np.uint64(0)  # unsigned: array stores without negative-index handling
    ng = valid = 0
    wraps = glitches = clamped = maxstep = other = unknown = oog = before = 0
    for i in range(w.size):
        v = np.int64(w[i])
        k = v >> 28
        if k <= 1:  # CD_OFF / CD_ON
            if th < 0:
                before += 1
                _note(defect, i, 3, 0)
                continue
            te = tbase + (th << 6) + ((v >> 22) & 0x3F)
            if te < last_t:
                clamped += 1
                maxstep = max(maxstep, last_t - te)
                te = last_t
            else:
                last_t = te
            valid += 1
            col = (v >> 11) & 0x7FF
            row = v & 0x7FF
            if col < width and row < height:
                if emit:
                    x[n] = col
                    y[n] = row
                    p[n] = k
                    t[n] = te
                n += np.uint64(1)
            else:
                oog += 1
                _outside(defect, i, col, row)
        elif k == 8:  # TIME_HIGH: a fall of more than half the range is a wrap
            nv = v & 0x0FFFFFFF
            if th >= 0:
                if th - nv > (1 << 27):
                    epoch += 1
                    wraps += 1
                    tbase = epoch << 34
                elif th > nv:
                    glitches += 1
            th = nv
        elif k == 0xA:  # EXT_TRIGGER
            if th < 0:
                before += 1
                _note(defect, i, 5, 0)
                continue
            tg = tbase + (th << 6) + ((v >> 22) & 0x3F)
            if tg < last_g:
                clamped += 1
                maxstep = max(maxstep, last_g - tg)
                tg = last_g
            else:
                last_g = tg
            if emit:
                gt[ng] = tg
                gp[ng] = v & 1
                gid[ng] = (v >> 8) & 0x1F
            ng += 1
        elif k >= 0xE:  # OTHERS, CONTINUED
            other += 1
        else:  # reserved
            unknown += 1
            _note(defect, i, 1, k)
    st[0] = th
    st[1] = epoch
    st[2] = last_t
    st[3] = last_g
    events = np.int64(n)
    _count(cnt, events, ng, valid, wraps, glitches, clamped, maxstep, other, 0, unknown,
           oog, before, 0)  # fmt: skip
    return events, ng
