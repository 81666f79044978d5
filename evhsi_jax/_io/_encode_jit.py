"""Compiled (numba) EVT 3.0 encoder: the word plan of `_evt3_encode`, in one pass.

The items (CD events, and triggers placed before the CD events of their µs) are walked
in order. Before an item whose µs differs from the previous item's: the extra TIME_HIGH
words of a long gap (every multiple of 1024 steps, and 4095 before each multiple of
4096), a TIME_HIGH when the high 12 bits change, then a TIME_LOW. A CD event gets an
EVT_ADDR_Y when its row differs from the previous CD event's. Each *vector chain* (a
maximal run of equal µs, row and polarity with strictly increasing columns in
consecutive 12-wide windows) is found by looking ahead, and written as VECT_BASE_X + one
VECT_12 per window (VECT_8 for the last window when its mask fits 8 bits) when that is
shorter than one EVT_ADDR_X per event. The words are bit-identical to the NumPy plan's
(tested), block by block with the same carried state (previous item's time, previous
CD event's row).
"""

from __future__ import annotations

from typing import no_type_check

import numpy as np

from .._base import njit, readonly

__all__ = ["encode_block", "order_and_min"]

_ONE = np.uint64(1)  # word counts are unsigned (see `_encode`)


@njit(inline=True)
@no_type_check
def _time_words(ti, t_prev, h_prev, out, n, write):
    """Time words before an item at `ti` µs (≠ the previous item's); returns
    `(n, h_prev)`."""
    h = ti >> 12
    if t_prev < 0 or h != h_prev:
        if h > h_prev + 1:  # a long gap: waypoints (two merged arithmetic series)
            m = (h_prev // 1024 + 1) * 1024
            r = ((h_prev + 1) // 4096 + 1) * 4096 - 1
            while m < h or r < h:
                if r < m:
                    v = r
                    r += 4096
                else:
                    v = m
                    m += 1024
                if write:
                    out[n] = 0x8000 | (v & 0xFFF)
                n += _ONE
        if write:
            out[n] = 0x8000 | (h & 0xFFF)
        n += _ONE
        h_prev = h
    if write:
        out[n] = 0x6000 | (ti & 0xFFF)
    return n + _ONE, h_prev


@njit
@no_type_check
def _encode(t, x, y, p, gt, gp, gid, t_prev, y_prev, out, write):
    h_prev = t_prev >> 12 if t_prev >= 0 else 0
    ne = t.size
    ng = gt.size
    # link[a]: events a and a + 1 are in one chain. A branch-free first pass (it
    # vectorises); x // 12 is (x * 2731) >> 15 for x < 4096 (columns are < 2048).
    link = np.empty(ne, np.bool_)
    for a in range(ne - 1):
        xa = np.int32(x[a])
        xb = np.int32(x[a + 1])
        wa = (xa * np.int32(2731)) >> np.int32(15)
        wb = (xb * np.int32(2731)) >> np.int32(15)
        same = (t[a + 1] == t[a]) & (y[a + 1] == y[a]) & (p[a + 1] == p[a])
        link[a] = same & (xb > xa) & (wb <= wa + np.int32(1))
    n = np.uint64(0)  # unsigned: array stores without negative-index handling
    i = 0
    j = 0
    g_next = gt[0] if ng else -1
    while i < ne or j < ng:
        if j < ng and (i == ne or g_next <= t[i]):  # before CD events of its µs
            if g_next != t_prev:
                n, h_prev = _time_words(g_next, t_prev, h_prev, out, n, write)
                t_prev = g_next
            if write:
                out[n] = 0xA000 | (np.int64(gid[j]) << 8) | gp[j]
            n += _ONE
            j += 1
            if j < ng:
                g_next = gt[j]
            continue
        ti = t[i]
        yi = np.int64(y[i])
        pi = np.int64(p[i])
        e = i + 1  # the chain is [i, e)
        while e < ne and link[e - 1]:
            e += 1
        if t_prev < 0 or (ti >> 12) != h_prev:  # a new TIME_HIGH (rare)
            n, h_prev = _time_words(ti, t_prev, h_prev, out, n, write)
        else:  # a TIME_LOW when the µs changed: written, kept or not (no branch)
            if write:
                out[n] = 0x6000 | (ti & 0xFFF)
            n += np.uint64(ti != t_prev)
        t_prev = ti
        if write:  # the same for a row word
            out[n] = yi
        n += np.uint64(yi != y_prev)
        y_prev = yi
        w0 = np.int64(x[i]) // 12
        if np.int64(x[e - 1]) // 12 - w0 + 2 < e - i:  # vectors are shorter
            if write:
                out[n] = 0x3000 | (pi << 11) | (w0 * 12)
            n += _ONE
            a = i
            while a < e:  # one word per window
                wa = np.int64(x[a]) // 12
                mask = 0
                while a < e and np.int64(x[a]) // 12 == wa:
                    mask |= 1 << (np.int64(x[a]) - wa * 12)
                    a += 1
                if write:
                    vect_8 = a == e and mask < 256  # the chain's last window
                    out[n] = (0x5000 if vect_8 else 0x4000) | mask
                n += _ONE
        elif e == i + 1:
            if write:
                out[n] = 0x2000 | (pi << 11) | x[i]
            n += _ONE
        else:
            if write:
                for a in range(i, e):
                    out[n + np.uint64(a - i)] = 0x2000 | (pi << 11) | x[a]
            n += np.uint64(e - i)
        i = e
    return np.int64(n)


@njit
@no_type_check
def _order_and_min(t):
    falls = 0
    low = t[0]
    for i in range(1, t.size):  # no early exit: the loop vectorises
        falls += t[i] < t[i - 1]
        low = min(low, t[i])
    return falls == 0, low


def order_and_min(t: np.ndarray) -> tuple[bool, int]:
    """Whether `t` is non-decreasing, and its minimum (0 when empty), in one pass."""
    if t.size == 0:
        return True, 0
    ordered, low = _order_and_min(readonly(t, np.int64))
    return bool(ordered), int(low)


def _bound(t, gt, prev_t) -> int:
    """Words an encoded block can take: 5 per item, plus the long-gap waypoints."""
    h0 = 0 if prev_t is None else prev_t >> 12
    last = max(int(t[-1]) if t.size else 0, int(gt[-1]) if gt.size else 0)
    h1 = max(last >> 12, h0)
    waypoints = h1 // 1024 - h0 // 1024 + (h1 + 1) // 4096 - (h0 + 1) // 4096
    return 5 * (t.size + gt.size) + waypoints + 4


def encode_block(
    t, x, y, p, gt, gp, gid, prev_t, prev_y, *, buffer=None, write: bool = True
):
    """Encode one block of `_evt3_encode._blocks` (compiled).

    **Arguments:**

    - `t`, `x`, `y`, `p`: the block's CD events, time-ordered (and reordered if asked).
    - `gt`, `gp`, `gid`: its triggers, time-ordered.
    - `prev_t`, `prev_y`: time of the previous block's last item and row of its last CD
      event (`None` at the start).
    - `buffer`: a `uint16` array to write into when large enough (it is reused).
    - `write`: when False, only count the words.

    **Returns:** `(words, buffer)`: a view of the block's words in `buffer` (or their
    count when not `write`) and the buffer used.
    """
    cols = (
        readonly(t, np.int64),
        readonly(x, np.uint16),
        readonly(y, np.uint16),
        readonly(p, np.uint8),
        readonly(gt, np.int64),
        readonly(gp, np.uint8),
        readonly(gid, np.uint8),
    )
    st = (-1 if prev_t is None else int(prev_t), -1 if prev_y is None else int(prev_y))
    if not write:
        return _encode(*cols, *st, np.empty(0, np.uint16), False), buffer
    size = _bound(cols[0], cols[4], prev_t)
    if buffer is None or buffer.size < size:
        buffer = np.empty(size, np.uint16)
    n = _encode(*cols, *st, buffer, True)
    return buffer[:n], buffer
