"""Vectorised EVT 3.0 encoding: `EventStream` → 16-bit words → `.raw` file.

Word plan, per *item* (a CD event or a trigger, merged in time order; triggers go before
the CD events of the same µs):

1. time words when the µs changes: TIME_HIGH when the high 12 bits change, then always a
   TIME_LOW (so a reader never depends on whether TIME_HIGH resets the low part);
2. for CD events, EVT_ADDR_Y when the row differs from the previous CD event's row;
3. the event itself: EVT_ADDR_X, or — inside a *vector chain* — VECT_BASE_X at the
   chain start and one VECT_12 per 12-column window (VECT_8 for a chain's last window
   when its mask fits in 8 bits);
4. for triggers, one EXT_TRIGGER word (channel id 0..15, edge value 0/1).

**Order.** Events keep exactly the order they are given in (time order is required; an
unsorted stream is stably sorted by time first), so write → read is the identity, order
included. A *vector chain* is a maximal run of consecutive events with equal time, row
and polarity, strictly increasing `x`, and columns in consecutive 12-wide windows
(`x // 12`); it is vectorised only when that is shorter (`1 + windows < events`).
`reorder=True` first sorts each µs by (row, polarity, column), which lets more events
share vector words; events of one µs may then come back in that order instead.

**Long gaps and wraps.** The 24-bit time wraps every 16.78 s. Readers disagree on how to
detect a wrap (any TIME_HIGH fall; a fall of more than half the range, as ours; or only
a near-full fall 4095 → 0, as `evt3` and Metavision do), so across a gap we insert extra
TIME_HIGH words at every multiple of 1024 high steps (4.19 s) and, before each multiple
of 4096, the value 4095: every TIME_HIGH step is then at most 1024 forward, and each
wrap is an adjacent 4095 → 0 pair, which all three rules decode the same way. The first
TIME_HIGH is reached from time 0 the same way, so absolute times beyond 16.78 s survive
too.

With the compiled kernels (`_numba`, the default) each block is encoded by
`_encode_jit.encode_block` into one reused buffer instead of the `(items, 5)` table;
the words are the same.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import numpy as np

from .._base import atomic_write
from .._base import numba_kernels as _numba
from .._model import EventStream
from ._header import format_header

__all__ = ["encode_evt3_words", "evt3_word_count", "write_evt3", "MAX_EVT3_SIZE"]

MAX_EVT3_SIZE = 2048  # 11-bit addresses
BLOCK_EVENTS = 1 << 20  # events encoded at a time


def _check(events: EventStream) -> bool:
    """Raise if `events` cannot be stored; returns whether they are time-ordered."""
    if events.width > MAX_EVT3_SIZE or events.height > MAX_EVT3_SIZE:
        raise ValueError(
            f"EVT 3.0 addresses are 11 bits: geometry {events.width}x{events.height} "
            f"exceeds {MAX_EVT3_SIZE}x{MAX_EVT3_SIZE}"
        )
    if _numba.use_numba():  # both in one pass, without temporaries
        from ._encode_jit import order_and_min

        ordered, t_min = order_and_min(events.t_us)
    else:
        ordered = events.is_time_ordered()
        t_min = int(events.t_us.min()) if len(events) else 0
    if t_min < 0:
        raise ValueError("EVT 3.0 cannot store negative timestamps")
    if events.trigger_t_us.size:
        if int(events.trigger_t_us.min()) < 0:
            raise ValueError("EVT 3.0 cannot store negative trigger timestamps")
        if int(events.trigger_id.max()) > 15 or int(events.trigger_p.max()) > 1:
            raise ValueError("EVT 3.0 triggers need id in 0..15 and value 0/1")
    return ordered


def _waypoints(a: int, b: int) -> np.ndarray:
    """Extra TIME_HIGH values strictly between high values `a < b` (see module doc)."""
    m = np.arange((a // 1024 + 1) * 1024, b, 1024, dtype=np.int64)
    wraps = np.arange(((a + 1) // 4096 + 1) * 4096, b + 1, 4096, dtype=np.int64) - 1
    return np.sort(np.concatenate([m, wraps]))


_SLOTS = 5  # per item, in order: TIME_HIGH, TIME_LOW, ADDR_Y, VECT_BASE_X, event word


def _blocks(
    events: EventStream, reorder: bool, ordered: bool | None = None
) -> Iterator[tuple]:
    """The stream cut into blocks of about `BLOCK_EVENTS` events at µs boundaries (so
    no vector chain is cut), each with the triggers of its time span and the time and
    row of the previous block's last item: blocks encode independently, and the
    temporaries stay small (fresh large allocations are costly). `ordered`: what
    `_check` returned, when already called."""
    if ordered is None:
        ordered = _check(events)
    ev = events if ordered else events.sorted_by_time()
    gt, gp, gid = ev.trigger_t_us, ev.trigger_p, ev.trigger_id
    if gt.size and np.any(np.diff(gt) < 0):
        order = np.argsort(gt, kind="stable")
        gt, gp, gid = gt[order], gp[order], gid[order]
    t = ev.t_us
    cuts = [0]
    while cuts[-1] + BLOCK_EVENTS < t.size:  # cut where the µs changes
        i = cuts[-1] + BLOCK_EVENTS
        c = int(np.searchsorted(t, t[i], side="left"))
        if c <= cuts[-1]:  # a single µs longer than a block: cut after it
            c = int(np.searchsorted(t, t[i], side="right"))
        cuts.append(c)
    if cuts[-1] < t.size or len(cuts) == 1:
        cuts.append(t.size)
    g_cuts = [0] + [int(np.searchsorted(gt, t[c], side="left")) for c in cuts[1:-1]]
    g_cuts.append(gt.size)
    prev_t = prev_y = None
    for b in range(len(cuts) - 1):
        sl, gs = slice(cuts[b], cuts[b + 1]), slice(g_cuts[b], g_cuts[b + 1])
        x, y, p, tb = ev.x[sl], ev.y[sl], ev.p[sl], t[sl]
        if reorder and tb.size:  # sorting within each µs never crosses a block
            o = np.lexsort((x, p, y, tb))
            x, y, p, tb = x[o], y[o], p[o], tb[o]
        yield tb, x, y, p, gt[gs], gp[gs], gid[gs], prev_t, prev_y
        if tb.size or gt[gs].size:
            last_t = max(tb[-1] if tb.size else -1, gt[gs][-1] if gt[gs].size else -1)
            prev_t = int(last_t)
        if y.size:
            prev_y = int(y[-1])


def _plan(t, x, y, p, gt, gp, gid, prev_t, prev_y, values: bool) -> tuple:
    """The words of each item of one block, as a `(items, 5)` table of candidate words
    `W` (only when `values`), a mask `M` of the words present, and the extra TIME_HIGH
    words `(item, values)` that go before some items. Reading `W[M]` row by row is the
    stream. `prev_t`, `prev_y`: time and row of the previous block's last item (or None).
    """
    ne = t.size
    ng = gt.size

    # Items: triggers merged before the CD events of the same µs.
    if ng:
        ins = np.searchsorted(t, gt, side="left")
        trig_item = ins + np.arange(ng)
        ev_item = np.arange(ne) + np.searchsorted(ins, np.arange(ne), side="right")
        it = np.empty(ne + ng, np.int64)
        it[ev_item] = t
        it[trig_item] = gt
    else:
        it = t
    n = it.size
    M = np.zeros((n, _SLOTS), bool)
    W = np.empty((n, _SLOTS), np.uint16) if values else None
    if n == 0:
        return W, M, []
    h = it >> 12
    h_prev = 0 if prev_t is None else prev_t >> 12
    M[0, 0] = prev_t is None or h[0] != h_prev
    M[0, 1] = prev_t is None or it[0] != prev_t
    np.not_equal(h[1:], h[:-1], out=M[1:, 0])
    np.not_equal(it[1:], it[:-1], out=M[1:, 1])
    # Long gaps (and a first time beyond 4.19 s): extra TIME_HIGH words.
    gaps = np.flatnonzero(h[1:] > h[:-1] + 1) + 1
    if h[0] > h_prev + 1:
        gaps = np.concatenate([[0], gaps])
    extra = [
        (int(i), _waypoints(int(h[i - 1]) if i else h_prev, int(h[i]))) for i in gaps
    ]
    if values:  # only the rows that use them
        i = np.flatnonzero(M[:, 0])
        W[i, 0] = 0x8000 | (np.take(h, i) & 0xFFF)
        i = np.flatnonzero(M[:, 1])
        W[i, 1] = 0x6000 | (np.take(it, i) & 0xFFF)

    # CD events: rows, vector chains (runs of one µs, row and polarity, increasing
    # columns in consecutive 12-wide windows) and windows.
    ny = np.ones(ne, bool)
    np.not_equal(y[1:], y[:-1], out=ny[1:])
    if ne and prev_y is not None:
        ny[0] = y[0] != prev_y
    win = x // np.uint16(12)
    brk = np.ones(ne, bool)
    if ne > 1:
        brk[1:] = (
            (t[1:] != t[:-1])
            | ny[1:]
            | (p[1:] != p[:-1])
            | (x[1:] <= x[:-1])
            | (win[1:] > win[:-1] + np.uint16(1))
        )
    cstart = np.flatnonzero(brk)
    k = np.diff(np.append(cstart, ne))
    nwin = win[cstart + k - 1].astype(np.int64) - win[cstart] + 1
    is_vec = np.repeat(nwin + 1 < k, k)  # vectors only where they are shorter
    ws = brk.copy()
    ws[1:] |= win[1:] != win[:-1]
    m_vb = is_vec & brk
    m_wx = ~is_vec | ws
    rows = slice(None) if not ng else ev_item
    M[rows, 2] = ny
    M[rows, 3] = m_vb
    M[rows, 4] = m_wx
    if ng:
        M[trig_item, 4] = True
    if values:
        pb = p.astype(np.uint16) << np.uint16(11)
        base = win * np.uint16(12)
        W[rows, 2] = y
        W[rows, 3] = np.uint16(0x3000) | pb | base
        wx = np.uint16(0x2000) | pb | x
        if is_vec.any():
            wstart = np.flatnonzero(ws)
            bit = np.left_shift(np.uint16(1), x - base)
            masks = np.bitwise_or.reduceat(bit, wstart)
            last = np.ones(wstart.size, bool)
            last[:-1] = brk[wstart[1:]]
            kind = np.where(last & (masks < 256), np.uint16(0x5000), np.uint16(0x4000))
            vw = wstart[is_vec[wstart]]
            wx[vw] = (kind | masks)[is_vec[wstart]]
        W[rows, 4] = wx
        if ng:
            W[trig_item, 4] = np.uint16(0xA000) | (gid.astype(np.uint16) << 8) | gp
    return W, M, extra


def evt3_word_count(events: EventStream, *, reorder: bool = False) -> int:
    """The exact number of 16-bit words `write_evt3` emits for `events` (no header).

    **Arguments:**

    - `events`: the stream.
    - `reorder`: as for `write_evt3`.

    **Returns:** the word count (bytes = 2 × words).
    """
    total = 0
    if _numba.use_numba():
        from ._encode_jit import encode_block

        for block in _blocks(events, reorder):
            total += encode_block(*block, write=False)[0]
        return int(total)
    for block in _blocks(events, reorder):
        _, M, extra = _plan(*block, values=False)
        total += int(np.count_nonzero(M)) + sum(v.size for _, v in extra)
    return total


def encode_evt3_words(events: EventStream, *, reorder: bool = False) -> np.ndarray:
    """Encode a stream as EVT 3.0 words (no header).

    **Arguments:**

    - `events`: the stream; width and height at most 2048 (11-bit addresses),
      timestamps ≥ 0, trigger ids 0..15.
    - `reorder`: sort each µs by (row, polarity, column) first, for more vector words.

    **Returns:** `uint16` array of words in file order.
    """
    parts = [w.copy() for w in _encode_blocks(events, reorder)]
    return np.concatenate(parts) if parts else np.zeros(0, np.uint16)


def _encode_blocks(
    events: EventStream, reorder: bool, ordered: bool | None = None
) -> Iterator[np.ndarray]:
    """The words block by block (valid until the next block is asked for: the
    compiled path reuses one buffer)."""
    if _numba.use_numba():
        from ._encode_jit import encode_block

        buffer = None
        for block in _blocks(events, reorder, ordered):
            words, buffer = encode_block(*block, buffer=buffer)
            yield words
        return
    for block in _blocks(events, reorder, ordered):
        W, M, extra = _plan(*block, values=True)
        out = W[M]
        if extra:
            rows = np.count_nonzero(M, axis=1)
            before = np.cumsum(rows) - rows
            at = np.concatenate([np.full(v.size, before[i]) for i, v in extra])
            vals = np.concatenate([0x8000 | (v & 0xFFF) for _, v in extra])
            out = np.insert(out, at, vals.astype(np.uint16))
        yield out


def write_evt3(
    path: str | os.PathLike,
    events: EventStream,
    *,
    reorder: bool = False,
    extra_header: dict | None = None,
) -> None:
    """Write `events` as a Prophesee EVT 3.0 `.raw` file, atomically.

    **Arguments:**

    - `path`: destination; written whole or not at all (`atomic_write`).
    - `events`: the stream (see `encode_evt3_words` for limits).
    - `reorder`: see `encode_evt3_words`.
    - `extra_header`: more `% key value` header lines.
    """
    header = format_header("evt3", events.width, events.height, extra_header)
    ordered = _check(events)  # before the file is created

    def fill(f) -> None:
        f.write(header)
        for words in _encode_blocks(events, reorder, ordered):  # block by block
            f.write(words.astype("<u2", copy=False).data)

    atomic_write(path, fill)
