"""Host-side bookkeeping: events → per-pixel padded event lists, grouped by count.

A pixel's work must follow its own event count, not the busiest pixel's. Pixels are
therefore grouped into *buckets* of padded length K ∈ {16, 32, 64, …}; each bucket is cut
into chunks of a fixed number of pixels, so every chunk of a bucket has the same static
shape and one compilation per bucket size serves the whole image. Pixels without events
are not put in any bucket (they cost no solve).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._base import shard, stable_argsort_int, use_numba
from .._model import EventStream

__all__ = [
    "PixelBatch", "PixelEvents", "group_pixels", "pixel_lists", "bucket_sizes",
    "bucket_plan",
]  # fmt: skip

MIN_BUCKET = 16
TIMESTAMP_CENTRE_US = 0.5


def bucket_sizes(max_count: int) -> list[int]:
    """Padded lengths 16, 32, 64, … up to the first one ≥ `max_count`."""
    sizes = [MIN_BUCKET]
    while sizes[-1] < max_count:
        sizes.append(sizes[-1] * 2)
    return sizes


@dataclasses.dataclass(frozen=True)
class PixelBatch:
    """Padded event lists of `n` pixels, `k` slots each (one static shape).

    - `pixel`: flat pixel index `y * width + x`, shape `(n,)` (-1 for padding rows).
    - `column`: pixel column, shape `(n,)`.
    - `t_us`: event times relative to the recording start, µs, float64, shape `(n, k)`:
      the integer timestamp plus `TIMESTAMP_CENTRE_US` (a sensor timestamp is the
      counter value when the event is detected, truncated to the µs, so the crossing
      happened within [t, t + 1); its expectation is t + 0.5 — a 1 % effect on a steep
      flank).
    - `polarity`: ±1 (0 in padding), int8, shape `(n, k)`.
    - `mask`: True for real events, shape `(n, k)`.
    - `count`: events per pixel, shape `(n,)`.
    """

    pixel: np.ndarray
    column: np.ndarray
    t_us: np.ndarray
    polarity: np.ndarray
    mask: np.ndarray
    count: np.ndarray

    @property
    def size(self) -> tuple[int, int]:
        return self.t_us.shape


class PixelEvents(eqx.Module):
    """What the per-pixel problem needs of a pixel besides the rig, on the device.

    For one pixel `t_us`, `polarity`, `mask` have shape `(k,)` and the rest are
    scalars; a batch adds leading axes (`jax.vmap`/`lax.map` over it, `jax.tree.map`
    to cut or reshape it).

    - `t_us`: event times relative to the recording start, µs (padded at the end).
    - `polarity`: ±1 per event (0 in padding); `mask`: real events.
    - `column_offset_us`: τx of the pixel's column.
    - `threshold_on`, `threshold_off`: the pixel's thresholds (log units).
    - `t0_phase_us`: the recording start modulo the sweep period.
    """

    t_us: Float[Array, "*n k"]
    polarity: Int[Array, "*n k"]
    mask: Bool[Array, "*n k"]
    column_offset_us: Float[ArrayLike, "*n"]
    threshold_on: Float[ArrayLike, "*n"]
    threshold_off: Float[ArrayLike, "*n"]
    t0_phase_us: Float[ArrayLike, "*n"]

    @classmethod
    def batch(
        cls, t_us, polarity, mask, column_offset_us, threshold_on, threshold_off,
        t0_phase_us=0.0,
    ) -> PixelEvents:  # fmt: skip
        """A batch of `n` pixels; scalar per-pixel values are broadcast to `(n,)`."""
        t_us = jnp.asarray(t_us)
        n = t_us.shape[0]

        def per_pixel(v):
            return jnp.broadcast_to(jnp.asarray(v, t_us.dtype), (n,))

        return cls(
            t_us,
            jnp.asarray(polarity),
            jnp.asarray(mask),
            per_pixel(column_offset_us),
            per_pixel(threshold_on),
            per_pixel(threshold_off),
            per_pixel(t0_phase_us),
        )


def group_pixels(
    events: EventStream,
    *,
    t_start_us: int | None = None,
    chunk_pixels: int = 1024,
    min_chunk: int | None = None,
    max_events: int | None = None,
    merge_below: int = 0,
    lists=None,
):
    """Cut an event stream into per-pixel padded batches.

    **Arguments:**

    - `events`: the stream (time-ordered).
    - `t_start_us`: recording start (the time the pixels' references were set); default
      the first trigger if any, else the first event, rounded down to a sweep start by
      the caller if needed.
    - `chunk_pixels`: pixels per batch.
    - `min_chunk`: the last batch of a bucket is padded only to `min_chunk` times a
      power of two (≤ `chunk_pixels`), not to a full chunk, so small buckets cost little;
      default `chunk_pixels` (every batch the same size).
    - `max_events`: keep at most this many events per pixel (the earliest).
    - `merge_below`: a bucket with fewer pixels than this joins the next larger one
      (padded to its length) instead of making batches of its own shape: one compiled
      shape less (a trace of ~0.8 s and a compilation) for a little padding.
    - `lists`: the stream's :func:`pixel_lists` from `t_start_us` when the caller has
      them already (possibly with times moved: `reconstruct`'s per-sweep speed).

    With numba (the default where it imports; `EVHSI_NO_NUMBA=1` turns it off) the
    sort by pixel is a counting sort (:func:`evhsi_jax._base.stable_argsort_int`) and
    the slots are filled in one pass (`_group_jit`); the NumPy path is the reference
    and gives the same batches.

    **Returns:** `(batches, counts, t0)` — a list of :class:`PixelBatch`, the event count
    of every pixel `(H*W,)`, and the start time used.
    """
    w = events.width
    if t_start_us is None:
        if events.trigger_t_us.size:
            t_start_us = int(events.trigger_t_us[0])
        elif len(events):
            t_start_us = int(events.t_us[0])
        else:
            t_start_us = 0
    jit = None
    if use_numba():
        from . import _group_jit as jit
    if lists is None:
        lists = pixel_lists(events, t_start_us)
    counts, starts, t_rel, sgn = lists
    use = counts if max_events is None else np.minimum(counts, max_events)
    batches = []
    for sel, k, size in bucket_plan(use, chunk_pixels, min_chunk, merge_below):
        n_pad = size - sel.size
        if jit is not None:
            tt = np.zeros((size, k), np.float64)
            pp = np.zeros((size, k), np.int8)
            mask = np.zeros((size, k), bool)
            jit.fill_slots(sel, starts, use, t_rel, sgn, tt, pp, mask)
        else:
            slot = np.arange(k)
            idx = starts[sel][:, None] + slot[None, :]
            mask = slot[None, :] < use[sel][:, None]
            idx = np.where(mask, idx, 0)
            tt = np.pad(np.where(mask, t_rel[idx], 0.0), ((0, n_pad), (0, 0)))
            pp = np.pad(
                np.where(mask, sgn[idx], 0).astype(np.int8), ((0, n_pad), (0, 0))
            )
            mask = np.pad(mask, ((0, n_pad), (0, 0)))
        batches.append(
            PixelBatch(
                pixel=np.pad(sel, (0, n_pad), constant_values=-1),
                column=np.pad(sel % w, (0, n_pad)),
                t_us=tt,
                polarity=pp,
                mask=mask,
                count=np.pad(use[sel], (0, n_pad)),
            )
        )
    return batches, counts, t_start_us


def bucket_plan(use, chunk_pixels: int, min_chunk: int | None = None,
                merge_below: int = 0) -> list[tuple[np.ndarray, int, int]]:  # fmt: skip
    """How :func:`group_pixels` cuts pixels with `use[p]` events into batches: a list
    of `(pixels, k, size)` — the flat indices of a batch's pixels (ascending), its
    slots per pixel and its padded number of rows (see `group_pixels` for
    `chunk_pixels`, `min_chunk` and `merge_below`). Pixels without events are in
    none."""
    plan = []
    active = np.nonzero(use > 0)[0]
    if active.size == 0:
        return plan
    sizes = bucket_sizes(int(use[active].max()))
    lower = 0
    carried = active[:0]
    for i, k in enumerate(sizes):
        members = active[(use[active] > lower) & (use[active] <= k)]
        members = np.sort(np.concatenate([carried, members]))
        lower = k
        if i + 1 < len(sizes) and 0 < members.size < merge_below:
            carried = members  # too few for a batch of their own: pad them to 2k
            continue
        carried = active[:0]
        for c0 in range(0, members.size, chunk_pixels):
            sel = members[c0 : c0 + chunk_pixels]
            size = chunk_pixels
            if min_chunk and sel.size < chunk_pixels:
                size = min_chunk
                while size < sel.size:
                    size *= 2
                size = min(size, chunk_pixels)
            plan.append((sel, k, size))
    return plan


#: Events from which :func:`pixel_lists` runs its passes on every usable core (at most
#: 8): below, one thread's passes take milliseconds.
THREADED_LISTS_MIN = 1 << 20


def pixel_lists(events: EventStream, t_start_us: int):
    """Every pixel's events, in pixel order and time order within a pixel.

    **Returns:** `(counts, starts, t_us, sign)` — events per pixel `(H*W,)`, where each
    pixel's events start `(H*W,)`, their times relative to `t_start_us` plus
    `TIMESTAMP_CENTRE_US` (float64) and polarities ±1 (int8): pixel p's events are
    `t_us[starts[p] : starts[p] + counts[p]]`, in time order. With numba one pass
    counts and one fills the lists (`_group_jit.pixel_lists`), each pass split over
    the usable cores from `THREADED_LISTS_MIN` events on (the same arrays); the NumPy
    path (a stable index sort, then gathers) is the reference, and takes a recording
    with times more than `_group_jit.LIST_MAX_SPAN_US` (~1.1 years) from
    `t_start_us`, which the numba path's packing cannot hold."""
    w, h = events.width, events.height
    if use_numba() and len(events):
        from . import _group_jit

        args = (
            events.x, events.y, events.t_us, events.p, np.int64(w), np.int64(w * h),
            np.int64(t_start_us), TIMESTAMP_CENTRE_US,
        )  # fmt: skip
        workers = min(shard.usable_cores(), 8)
        if workers > 1 and len(events) >= THREADED_LISTS_MIN:
            with concurrent.futures.ThreadPoolExecutor(workers) as pool:
                *lists, far = _group_jit.pixel_lists_threaded(*args, pool, workers)
        else:
            *lists, far = _group_jit.pixel_lists(*args)
        if not far:  # (else times over a year apart: the NumPy path below)
            return tuple(lists)
    pix = events.y.astype(np.int64) * w + events.x.astype(np.int64)
    counts = np.bincount(pix, minlength=w * h)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    if pix.size == 0:
        return counts, starts, np.zeros(0), np.zeros(0, np.int8)
    order = stable_argsort_int(pix)
    t_rel = (events.t_us[order] - t_start_us).astype(np.float64) + TIMESTAMP_CENTRE_US
    sgn = np.asarray(events.polarity_sign[order], np.int8)
    return counts, starts, t_rel, sgn


#: Longest recording (µs from its start) whose times :class:`DeviceLists` keeps as
#: int32; a longer one is grouped on the host.
DEVICE_MAX_SPAN_US = 2**31 - 1


class DeviceLists:
    """Every pixel's events sorted by pixel on the accelerator, and the padded
    batches of :func:`bucket_plan` gathered there — what :func:`group_pixels` and
    `_pipeline._device_pixels` do on the host, without the host's per-event passes or
    the transfer of padded arrays (a GPU sorts 25 M events in milliseconds).

    The events go to the device once as (x, y, time from the start in int32, polarity);
    the number of events is padded to a power of two (few compiled shapes) with
    entries that sort last. Only the per-pixel counts come back (the plan is made on
    the host). `keep`: optionally a bool per event, the events to use (the others
    go over as padding: the screening's drop without a copy of the kept events on
    the host). A batch's times are `float(t) + TIMESTAMP_CENTRE_US + lead` in the
    batch's dtype: bit for bit the host's `float(t + 0.5 + lead)` when `lead` is 0
    and t < 2^23 µs (float32), else within a rounding of it.
    """

    def __init__(self, events: EventStream, t_start_us: int, keep=None):
        w, h = events.width, events.height
        x, y, t_rel, p = _padded_for_device(events, t_start_us, keep)
        counts, starts, t_s, s_s = _sort_by_pixel(*jax.device_put((x, y, t_rel, p)), w,
                                                  w * h)  # fmt: skip
        self.counts = np.asarray(counts).astype(np.int64)  # (the host's plan)
        self.counts_device, self.starts = counts, starts
        self.t_sorted, self.s_sorted = t_s, s_s
        self.width = w

    @staticmethod
    def fits(events: EventStream, t_start_us: int) -> bool:
        """Whether the recording's span fits the int32 times."""
        return len(events) == 0 or (
            int(events.t_us[-1]) - int(t_start_us) <= DEVICE_MAX_SPAN_US
            and int(events.t_us[0]) >= int(t_start_us)
        )

    def batch(self, sel, k, size, lead, offsets, thr_on, thr_off, dtype, speed=None):
        """The :class:`PixelEvents` of the pixels `sel` (ascending flat indices) with
        `k` slots, padded to `size` rows, on the device. `lead`, `offsets`,
        `thr_on`, `thr_off`: the device copies of the per-pixel clock shift, the
        per-column offsets and the per-pixel thresholds (in `dtype`). `speed`:
        optionally `(factors, period_us)`, each sweep's mirror-speed factor (a device
        array) and the period: the times are then moved as
        :func:`._sweep_speed.warp_times` moves them (in `dtype`).

        **Returns:** `(pixel, pixel_device, events)` — the padded flat indices (−1 for
        padding) on the host and their int32 copy on the device (sent once), and the
        batch."""
        pixel = np.full(size, -1, np.int32)
        pixel[: sel.size] = sel
        pixel_device = jax.device_put(pixel)
        factors, period = (None, 0.0) if speed is None else speed
        return pixel.astype(np.int64), pixel_device, _gather_batch(
            self.t_sorted, self.s_sorted, self.starts, self.counts_device,
            pixel_device, lead, offsets, thr_on, thr_off, factors, period, k,
            self.width, np.dtype(dtype).name,
        )  # fmt: skip


def _padded_for_device(events: EventStream, t_start_us: int, keep=None):
    """`(x, y, t_rel, p)` of :class:`DeviceLists`: the events' columns, rows, int32
    times from `t_start_us` and polarities, padded to a power of two (at least 1024)
    with events at row H (past the last pixel: they sort last), as are the events
    whose `keep` is False. From
    `THREADED_LISTS_MIN` events on, slices are filled on the usable cores (at most
    8; NumPy's copies release the GIL, and the fresh arrays' pages are then touched
    by several cores): the same arrays."""
    n, h = len(events), events.height
    n_pad = 1 << max(int(n - 1).bit_length(), 10)
    t_rel = np.empty(n_pad, np.int32)  # (no int64 temporary: `fits` checked)
    x, y, p = (np.empty(n_pad, a.dtype) for a in (events.x, events.y, events.p))

    def part(i0, i1):  # the events' slots of [i0, i1), then the padding's
        e1 = min(i1, n)
        np.subtract(events.t_us[i0:e1], t_start_us, out=t_rel[i0:e1], casting="unsafe")
        x[i0:e1], y[i0:e1], p[i0:e1] = events.x[i0:e1], events.y[i0:e1], events.p[i0:e1]
        if keep is not None:
            np.copyto(y[i0:e1], h, where=~keep[i0:e1])
        p0 = max(i0, n)
        t_rel[p0:i1], x[p0:i1], p[p0:i1], y[p0:i1] = 0, 0, 0, h

    shard.in_slices(n_pad, part, threaded=n >= THREADED_LISTS_MIN)
    return x, y, t_rel, p


@functools.partial(jax.jit, static_argnums=(4, 5))
def _sort_by_pixel(x, y, t_rel, p, width, n_pix):
    """Counts per pixel `(n_pix,)`, where each pixel's events start, and the times
    and polarities (±1, int8) in pixel order, time order within a pixel (a stable
    sort of time-ordered events)."""
    pix = y.astype(jnp.int32) * width + x.astype(jnp.int32)
    order = jnp.argsort(pix, stable=True)
    counts = jnp.zeros(n_pix + 1, jnp.int32).at[pix].add(1, mode="drop")[:n_pix]
    starts = jnp.cumsum(counts) - counts
    sgn = (2 * p.astype(jnp.int8) - 1).astype(jnp.int8)
    return counts, starts, t_rel[order], sgn[order]


@functools.partial(jax.jit, static_argnums=(11, 12, 13))
def _gather_batch(t_sorted, s_sorted, starts, counts, pixel, lead, offsets, thr_on,
                  thr_off, factors, period, k, width, dtype):  # fmt: skip
    """The :class:`PixelEvents` of the rows `pixel` (−1: padding) with `k` slots, as
    `_pipeline._device_pixels` makes them from the host's batch (`factors`: None,
    or each sweep's mirror-speed factor, the times then moved by it)."""
    valid = pixel >= 0
    p = jnp.where(valid, pixel, 0)
    slot = jnp.arange(k)
    use = jnp.where(valid, counts[p], 0)
    mask = slot[None, :] < use[:, None]
    idx = jnp.where(mask, starts[p][:, None] + slot[None, :], 0)
    d = jnp.where(valid, lead[p], 0).astype(dtype)
    t = t_sorted[idx].astype(dtype) + jnp.asarray(TIMESTAMP_CENTRE_US, dtype)
    if factors is not None:  # (_sweep_speed.warp_times, on the device)
        period = jnp.asarray(period, dtype)
        s = jnp.floor(t / period)
        f = factors.astype(dtype)[jnp.clip(s, 0, factors.size - 1).astype(jnp.int32)]
        tau = offsets[p % width].astype(dtype)[:, None]
        local = t - s * period
        moved = jnp.clip(f * (local + tau) - tau, 0.0, jnp.nextafter(period, 0.0))
        t = s * period + moved
    return PixelEvents(
        jnp.where(mask, t + d[:, None], 0).astype(dtype),
        jnp.where(mask, s_sorted[idx], 0).astype(jnp.int32),
        mask,
        offsets[p % width].astype(dtype),
        thr_on[p].astype(dtype),
        thr_off[p].astype(dtype),
        (-d).astype(dtype),
    )
