"""numba kernels of the host bookkeeping: :func:`._pixels.group_pixels` and the
screening of :func:`._pipeline.screen_events` (imported on first use).

Each replaces NumPy code that makes several passes over the events: the filling of a
bucket's padded slots (one pass over its pixels' events instead of a gather through an
`(n, k)` index array) and the screening (one pass instead of a remainder, six
comparisons and a bincount). The sort by pixel is the shared counting sort
(`evhsi_jax._base.stable_argsort_int`). The NumPy code in `_pixels` and `_pipeline` is
the reference; the tests run both. Kernels are marked `no_type_check` so that the
jaxtyping import hook of the test suite leaves them to numba.
"""

from __future__ import annotations

from typing import no_type_check

import numpy as np

from .._base import njit


@njit
@no_type_check
def fill_slots(sel, starts, use, t_sorted, s_sorted, tt, pp, mask):
    """Row r of the padded arrays gets the first `use[sel[r]]` events of pixel
    `sel[r]` (its events start at `starts[p]` of the sorted arrays)."""
    for r in range(sel.size):
        p = sel[r]
        s = starts[p]
        for j in range(use[p]):
            tt[r, j] = t_sorted[s + j]
            pp[r, j] = s_sorted[s + j]
            mask[r, j] = True


@njit
@no_type_check
def lit_mask(x, t_us, t_start_us, period, lo_col, hi_col, inside):
    """Per event, whether its time modulo the period falls in its column's interval
    `[lo_col, hi_col]` (which may wrap around the period), into `inside`: the
    screening of :func:`._pipeline.screen_events` in one pass (NumPy's floating
    remainder, to the bit: fmod, then the divisor's sign). Releases the GIL: the
    caller runs slices of the events on several threads."""
    for i in range(x.size):
        c = np.int64(x[i])
        r = np.float64(t_us[i]) - np.float64(t_start_us)
        local = np.fmod(r, period)
        if local != 0.0 and (local < 0.0) != (period < 0.0):
            local += period
        lo = lo_col[c]
        hi = hi_col[c]
        inside[i] = (
            (local >= lo and local <= hi)
            or (local + period >= lo and local + period <= hi)
            or (local - period >= lo and local - period <= hi)
        )


@njit
@no_type_check
def drop_hot(x, y, inside, hot, width, keep):
    """keep[i] = inside[i] and the event's pixel (y·W + x) is not `hot`; returns
    how many are kept. Releases the GIL (slices on several threads)."""
    n = 0
    for i in range(x.size):
        k = inside[i] and not hot[np.int64(y[i]) * width + np.int64(x[i])]
        keep[i] = k
        n += k
    return n


@njit
@no_type_check
def compact_events(keep, x, y, p, t, out_x, out_y, out_p, out_t, o0):
    """The events with `keep` set, in order, into the output arrays from index
    `o0` on (one slice of a parallel compaction: each slice's offset is the number
    kept before it)."""
    j = o0
    for i in range(keep.size):
        if keep[i]:
            out_x[j] = x[i]
            out_y[j] = y[i]
            out_p[j] = p[i]
            out_t[j] = t[i]
            j += 1


#: Pixels per block of :func:`pixel_lists`' partition pass (2^10: a block's events
#: fit in a core's L2 cache, the ~900 blocks' write positions in L1).
LIST_BLOCK_SHIFT = 10
#: Between the passes each event is one int64: its time from the start (signed,
#: the high bits), its pixel within its block and its polarity byte (the low
#: `LIST_LOW_BITS`). One write stream per block instead of three (times, polarities,
#: pixels): the distributing pass ran ~3x faster (25 M events, one thread, 0.20 →
#: 0.07 s), and the times are placed into the same memory, viewed as float64.
LIST_LOW_BITS = LIST_BLOCK_SHIFT + 8
#: The largest |time from the start| (µs) that fits beside them: ~1.1 years.
LIST_MAX_SPAN_US = (1 << (63 - LIST_LOW_BITS)) - 1


@njit
@no_type_check
def pixel_lists(x, y, t_us, p, width, n_pix, t_start_us, centre):
    """:func:`._pixels.pixel_lists` without an index sort: one pass counts the
    events per pixel, one distributes them (stably) to blocks of `2^LIST_BLOCK_SHIFT`
    consecutive pixels, and one per block puts each event at its pixel's next slot.

    A sweep's events at any moment come from all over the sensor (each column sees the
    whole rainbow), so placing them straight into their pixels' lists writes all over
    the output — a cache miss per event (1280x720 sweep, 25 M events: 1.2 s of the
    fill alone). Through the blocks both placing passes write to a few thousand
    sequential streams or into one cached block. Returns `(counts, starts, t_out,
    s_out, far)`: `far` events lay more than `LIST_MAX_SPAN_US` from `t_start_us`
    (their times do not fit the packing; the arrays are then not to be used)."""
    n = x.size
    counts = np.zeros(n_pix, np.int64)
    for i in range(n):
        counts[np.int64(y[i]) * width + np.int64(x[i])] += 1
    starts = np.empty(n_pix, np.int64)
    acc = 0
    for q in range(n_pix):
        starts[q] = acc
        acc += counts[q]
    shift = LIST_BLOCK_SHIFT
    n_blocks = (n_pix + (1 << shift) - 1) >> shift
    edge = np.empty(n_blocks + 1, np.int64)  # where each block's events start
    for b in range(n_blocks):
        edge[b] = starts[b << shift]
    edge[n_blocks] = n
    # Pass 2: events to their blocks, in time order within a block (the helpers are
    # those of the threaded version, below), packed one int64 each.
    packed = np.empty(n, np.int64)
    s_out = np.empty(n, np.int8)
    far = _slice_distribute(
        x, y, t_us, p, width, t_start_us, edge[:n_blocks].copy(), packed
    )  # fmt: skip
    # Pass 3: within each block, each event to its pixel's next slot; its time into
    # the same memory, as float64.
    # (np.int64(0), not the literal 0: one compiled _blocks_place for both callers)
    t_out = packed.view(np.float64)
    _blocks_place(
        np.int64(0), n_blocks, edge, starts.copy(), packed, t_out, s_out, centre
    )  # fmt: skip
    return counts, starts, t_out, s_out, far


# The same lists built on several threads (`pixel_lists_threaded`): the events cut
# into contiguous slices, each slice counted and distributed to the blocks by one
# thread (a slice's events go after the earlier slices' in each block, so the order
# stays the time order), then the blocks split between the threads for the last
# pass. The same arrays as `pixel_lists`, bit for bit.


@njit
@no_type_check
def _slice_counts(x, y, width, counts, block_counts):
    """Events per pixel and per block of one slice (into its own arrays)."""
    shift = LIST_BLOCK_SHIFT
    for i in range(x.size):
        q = np.int64(y[i]) * width + np.int64(x[i])
        counts[q] += 1
        block_counts[q >> shift] += 1


@njit
@no_type_check
def _slice_distribute(x, y, t_us, p, width, t_start_us, fill, packed):
    """Pass 2 of `pixel_lists` for one slice, from its own write positions `fill`:
    each event as `(t - t_start) << LIST_LOW_BITS | pixel in block << 8 | p`.
    Returns how many events lay beyond `LIST_MAX_SPAN_US` of the start."""
    shift = LIST_BLOCK_SHIFT
    far = 0
    for i in range(x.size):
        q = np.int64(y[i]) * width + np.int64(x[i])
        b = q >> shift
        j = fill[b]
        fill[b] = j + 1
        dt = np.int64(t_us[i]) - t_start_us
        if dt > LIST_MAX_SPAN_US or dt < -LIST_MAX_SPAN_US:
            far += 1
        packed[j] = (dt << LIST_LOW_BITS) | ((q - (b << shift)) << 8) | np.int64(p[i])
    return far


@njit
@no_type_check
def _blocks_place(b0, b1, edge, pos, packed, t_out, s_out, centre):
    """Pass 3 of `pixel_lists` for the blocks [b0, b1) (their pixels' write
    positions `pos` are theirs alone): each block's packed events copied out, then
    each one's time (+ `centre`, float64) and polarity (±1) written at its pixel's
    next slot. `t_out` may be `packed` itself viewed as float64: a block's slots are
    the ones its events were packed into."""
    shift = LIST_BLOCK_SHIFT
    in_block = (1 << shift) - 1
    longest = 0
    for b in range(b0, b1):
        longest = max(longest, edge[b + 1] - edge[b])
    tmp = np.empty(longest, np.int64)
    for b in range(b0, b1):
        lo = edge[b]
        m = edge[b + 1] - lo
        for k in range(m):
            tmp[k] = packed[lo + k]
        base = b << shift
        for k in range(m):
            v = tmp[k]
            q = base + ((v >> 8) & in_block)
            j = pos[q]
            pos[q] = j + 1
            t_out[j] = np.float64(v >> LIST_LOW_BITS) + centre
            s_out[j] = 2 * np.int8(v & 0xFF) - 1


def pixel_lists_threaded(x, y, t_us, p, width, n_pix, t_start_us, centre, pool,
                         workers):  # fmt: skip
    """:func:`pixel_lists` with each pass split over `workers` threads of `pool`."""
    n = x.size
    shift = LIST_BLOCK_SHIFT
    n_blocks = (n_pix + (1 << shift) - 1) >> shift
    cuts = np.linspace(0, n, workers + 1).astype(np.int64)
    sl = [slice(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    counts_s = np.zeros((workers, n_pix), np.int64)
    blocks_s = np.zeros((workers, n_blocks), np.int64)
    list(pool.map(lambda i: _slice_counts(x[sl[i]], y[sl[i]], width, counts_s[i],
                                          blocks_s[i]), range(workers)))  # fmt: skip
    counts = counts_s.sum(axis=0)
    starts = np.zeros(n_pix, np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    edge = np.empty(n_blocks + 1, np.int64)
    edge[:n_blocks] = starts[:: 1 << shift]
    edge[n_blocks] = n
    # Each slice writes after the earlier slices' events of the same block.
    fills = edge[:n_blocks] + np.cumsum(blocks_s, axis=0) - blocks_s
    packed = np.empty(n, np.int64)
    s_out = np.empty(n, np.int8)
    far = sum(pool.map(lambda i: _slice_distribute(
        x[sl[i]], y[sl[i]], t_us[sl[i]], p[sl[i]], width, t_start_us, fills[i],
        packed), range(workers)))  # fmt: skip
    if far:  # (the caller takes another path: see pixel_lists)
        return counts, starts, None, None, far
    # Blocks split so that each thread gets about the same number of events.
    bcut = np.searchsorted(edge, np.linspace(0, n, workers + 1)).clip(0, n_blocks)
    bcut[0], bcut[-1] = 0, n_blocks
    pos = starts.copy()
    t_out = packed.view(np.float64)
    list(pool.map(lambda i: _blocks_place(
        np.int64(bcut[i]), np.int64(bcut[i + 1]), edge, pos, packed, t_out, s_out,
        centre), range(workers)))  # fmt: skip
    return counts, starts, t_out, s_out, 0


@njit
@no_type_check
def warp_pixel_times(t_rel, starts, counts, width, offsets, period, factors, out):
    """:func:`._sweep_speed.warp_times` over the pixel lists (pixel p's events at
    `starts[p]`, `counts[p]` of them) in one pass: each event's sweep, local time and
    its column's τ without the per-event temporaries of the NumPy version (which made
    a 1280×720 `realistic` sweep's warp ~1 s). The same operations in the same order,
    so the same values."""
    top = np.nextafter(period, 0.0)
    last = factors.size - 1
    for p in range(counts.size):
        tau = offsets[p % width]
        for i in range(starts[p], starts[p] + counts[p]):
            t = t_rel[i]
            s = np.floor(t / period)
            local = t - s * period
            f = factors[min(max(np.int64(s), 0), last)]
            moved = f * (local + tau) - tau
            moved = min(max(moved, 0.0), top)
            out[i] = s * period + moved
