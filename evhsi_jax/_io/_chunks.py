"""The per-chunk containers shared by the decoders, and the format-independent steps.

Decoding a chunk has three steps: a per-word *scan* (format-specific) yields a
`ScannedChunk` with one row per *event word* and times relative to the chunk's first
epoch; `apply_time` makes the times absolute and non-decreasing (running maxima; it
must run in chunk order, and is cheap); `expand_events` turns the chunk into one row per
CD event and checks the geometry. Vector masks become bit positions with
`np.unpackbits` + `np.flatnonzero` (position // 16 is the word, position % 16 the column
offset) and every column is then one `np.take` by word; chunks without vector words skip
that step.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from .._model import EventStream
from ._report import DecodeError, DecodeReport

POPCOUNT12 = np.array([bin(i).count("1") for i in range(1 << 12)], np.uint8)

__all__ = [
    "DecodedChunk",
    "as_stream",
    "ScannedChunk",
    "apply_time",
    "concat_scanned",
    "expand_events",
]


class DecodedChunk(NamedTuple):
    """Columns decoded from one chunk (see `EventStream` for meanings and dtypes)."""

    x: np.ndarray
    y: np.ndarray
    p: np.ndarray
    t_us: np.ndarray
    trigger_t_us: np.ndarray
    trigger_p: np.ndarray
    trigger_id: np.ndarray

    @staticmethod
    def empty() -> DecodedChunk:
        return DecodedChunk(
            np.zeros(0, np.uint16),
            np.zeros(0, np.uint16),
            np.zeros(0, np.uint8),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0, np.uint8),
            np.zeros(0, np.uint8),
        )


_FIELDS = ("x", "y", "p", "t_us", "width", "height", "trigger_t_us", "trigger_p",
           "trigger_id")  # fmt: skip
_TRUSTED = tuple(f.name for f in dataclasses.fields(EventStream)) == _FIELDS


def as_stream(c: DecodedChunk, width: int, height: int) -> EventStream:
    """A decoded chunk as an `EventStream`, without validating it a second time.

    The decoders guarantee what `EventStream.__post_init__` checks (exact dtypes, equal
    lengths, coordinates inside the geometry, polarity 0/1, and times non-decreasing),
    and its eight reductions over the columns cost ~20 % of reading a large file. Should
    `EventStream` change its fields, the validating constructor is used instead.
    """
    if not _TRUSTED:
        return EventStream(*c[:4], width, height, *c[4:])
    ev = object.__new__(EventStream)
    for name, value in zip(_FIELDS, (*c[:4], int(width), int(height), *c[4:])):
        object.__setattr__(ev, name, value)
    return ev


class ScannedChunk(NamedTuple):
    """Per *event word* columns of one chunk, ready for `expand_events`.

    `mask` is `None` when every event word is an EVT_ADDR_X (one event each); else the
    bit mask of each word's events (1 for EVT_ADDR_X), and `base` the column of bit 0.
    """

    base: np.ndarray  # uint16
    pol: np.ndarray  # uint8
    y: np.ndarray  # uint16
    t: np.ndarray  # int64
    mask: np.ndarray | None  # uint16
    epos: np.ndarray  # word index of each event word, for messages
    byte_offset: int
    triggers: tuple
    wraps: int  # time-base wraps inside the chunk (times count them from 0)


def concat_scanned(
    parts: list[ScannedChunk], *, word_bytes: int, epoch_bits: int
) -> ScannedChunk:
    """Join consecutive scanned blocks of one chunk (positions and epochs made
    chunk-wide)."""
    first = parts[0]
    shifted, wraps = [], 0
    for p in parts:
        if wraps:
            off = wraps << epoch_bits
            t = np.where(p.t >= 0, p.t + off, p.t)
            trig = (p.triggers[0] + off, *p.triggers[1:])
            p = p._replace(t=t, triggers=trig)
        shifted.append(p)
        wraps += p.wraps
    parts = shifted
    masks = [p.mask for p in parts]
    if any(m is not None for m in masks):
        masks = [
            np.ones(p.epos.size, np.uint16) if p.mask is None else p.mask for p in parts
        ]
        mask = np.concatenate(masks)
    else:
        mask = None
    epos = np.concatenate(
        [p.epos + (p.byte_offset - first.byte_offset) // word_bytes for p in parts]
    )
    triggers = tuple(np.concatenate(cols) for cols in zip(*(p.triggers for p in parts)))
    return ScannedChunk(
        np.concatenate([p.base for p in parts]),
        np.concatenate([p.pol for p in parts]),
        np.concatenate([p.y for p in parts]),
        np.concatenate([p.t for p in parts]),
        mask,
        epos,
        first.byte_offset,
        triggers,
        wraps,
    )


def _running_max(t, weight, last: int, report: DecodeReport):
    """Running maximum of `t` from `last`; counts `weight` of the raised entries."""
    if t[0] >= last and bool((t[1:] >= t[:-1]).all()):
        return t  # already non-decreasing: the usual case, one cheap pass
    run = np.maximum.accumulate(t)
    np.maximum(run, last, out=run)
    stepped = run > t
    if weight is not None:
        stepped &= weight > 0
    if stepped.any():
        ns = stepped.sum() if weight is None else POPCOUNT12[weight[stepped]].sum()
        report.time_clamped += int(ns)
        report.max_step_back_us = max(
            report.max_step_back_us, int((run - t)[stepped].max())
        )
    return run


def apply_time(sc: ScannedChunk, offset_us: int, state, report: DecodeReport):
    """Make a scanned chunk's times absolute and non-decreasing, in chunk order.

    Adds `offset_us` (the time base of the chunk's first epoch) to every valid time,
    then applies the running maxima `state.last_t` (CD events; only words that carry
    events count) and `state.last_trig_t` (triggers), counting clamped entries in
    `report`, and updates both maxima.

    **Arguments:**

    - `sc`: the chunk, from a scan.
    - `offset_us`: `epoch << 24` (EVT 3.0) or `epoch << 34` (EVT 2.0), in µs.
    - `state`: any decoder state (has `last_t`, `last_trig_t`); updated.
    - `report`: counters, updated.

    **Returns:** the chunk with final times.
    """
    t, mask = sc.t, sc.mask
    if t.size:
        valid = None if mask is None or mask.all() else mask > 0
        if valid is not None:
            t = np.where(valid, t + offset_us, -1)
        elif offset_us:
            t = t + offset_us
        t = _running_max(t, mask, state.last_t, report)
        state.last_t = int(t[-1])
    gt = sc.triggers[0]
    if gt.size:
        gt = _running_max(gt + offset_us, None, state.last_trig_t, report)
        state.last_trig_t = int(gt[-1])
    return sc._replace(t=t, triggers=(gt, *sc.triggers[1:]))


def expand_events(
    sc: ScannedChunk,
    *,
    width: int,
    height: int,
    report: DecodeReport,
    strict: bool = False,
    word_bytes: int = 2,
    fmt: str = "EVT 3.0",
) -> DecodedChunk:
    """Stage 2 of decoding a chunk: one row per CD event, geometry checked.

    **Arguments:**

    - `sc`: the output of `scan_evt3_words` (or the EVT 2.0 scanner).
    - `width`, `height`: geometry; events outside it are skipped (or raise if `strict`).
    - `report`: counters (only `events` and `out_of_geometry` are touched here, so the
      two stages may run in different threads).
    - `strict`: raise `DecodeError` on an out-of-geometry event.
    - `word_bytes`, `fmt`: bytes per word and format name, for messages.

    **Returns:** the chunk's `DecodedChunk`.
    """
    if sc.mask is None:
        x, y, p, t = sc.base, sc.y, sc.pol, sc.t
        word = None
    else:
        bits = np.unpackbits(sc.mask.view(np.uint8), bitorder="little").view(bool)
        nz = np.flatnonzero(bits)
        word = nz >> 4
        x = np.take(sc.base, word)
        x += nz.astype(np.uint16) & np.uint16(15)
        y = np.take(sc.y, word)
        p = np.take(sc.pol, word)
        t = np.take(sc.t, word)
    if x.size and (int(x.max()) >= width or int(y.max()) >= height):
        bad = (x >= width) | (y >= height)
        if strict:
            k = int(np.flatnonzero(bad)[0])
            at = k if word is None else int(word[k])
            raise DecodeError(
                f"{fmt} stream: event ({int(x[k])}, {int(y[k])}) outside the "
                f"{width}x{height} geometry at byte "
                f"{sc.byte_offset + word_bytes * int(sc.epos[at])} (strict mode)"
            )
        good = ~bad
        report.out_of_geometry += int(bad.sum())
        x, y, p, t = x[good], y[good], p[good], t[good]
    report.events += int(x.size)
    return DecodedChunk(x, y, p, t, *sc.triggers)
