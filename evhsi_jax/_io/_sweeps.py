"""Splitting an event stream into sweeps (one hyperspectral frame per mirror sweep).

**Trigger convention.** A mirror encoder wired to the camera's trigger input marks each
sweep start with one rising edge on channel 0: a trigger event with `trigger_id == 0`
and `trigger_p == 1` at the start of sweep `k` (the simulator emits one at `t =
k·period_us`). Falling edges and other channels are ignored. Sweep `k` is `[trig_k,
trig_{k+1})`; the last one ends one median trigger interval after its start (or
`period_us` when there is a single trigger). Events before the first trigger belong to
no sweep (a partial sweep).

**Without triggers** the sweep period must be given; the phase (where one sweep ends and
the next starts) is estimated from the data as the centre of the quietest stretch of the
event-time histogram folded modulo the period — the dead time between sweeps, when the
band is off the scene — so no sweep is cut through its middle. Cuts are then at
`phase + k·period` (rounded to µs), covering every event.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np

from .._model import EventStream

__all__ = ["Sweeps", "SweepCutter", "split_sweeps", "estimate_sweep_phase"]


def _trigger_marks(events: EventStream, trigger_id: int, trigger_p: int = 1):
    """Sweep-start marks: the times of the stream's triggers on channel `trigger_id`
    with edge `trigger_p`, as they come (sorted for a time-ordered stream)."""
    sel = (events.trigger_id == trigger_id) & (events.trigger_p == trigger_p)
    return events.trigger_t_us[sel]


def _last_stop(marks: np.ndarray, period) -> int:
    """Where the last trigger-started sweep ends: one median trigger interval (or one
    `period` with a single trigger) after its start."""
    gaps = np.diff(marks)
    return int(marks[-1]) + int(round(float(np.median(gaps)) if gaps.size else period))


def _period_cut(phase_us, period_us, j):
    """The `j`-th cut of the period path, `phase + j·period` rounded to µs."""
    return np.round(phase_us + period_us * np.asarray(j)).astype(np.int64)


@dataclasses.dataclass(frozen=True, eq=False)
class Sweeps:
    """Sweep boundaries of a stream, and each sweep's events.

    **Arguments:**

    - `start_us`, `stop_us`: shape `(sweeps,)`, int64 µs; sweep `k` holds the events
      with `start_us[k] <= t < stop_us[k]`; `stop_us[k] <= start_us[k+1]`.
    - `source`: `"trigger"` or `"period"` (how the boundaries were found).
    - `period_us`: the nominal period (the median trigger interval for `"trigger"`).
    - `phase_us`: `start_us[0]` modulo `period_us`.
    - `events`: the stream that was split.

    `sweeps[k]` is sweep `k`'s `EventStream`; iterating yields them in order.
    """

    start_us: np.ndarray
    stop_us: np.ndarray
    source: str
    period_us: float
    phase_us: float
    events: EventStream

    def __len__(self) -> int:
        return int(self.start_us.size)

    def __getitem__(self, k: int | np.integer) -> EventStream:
        if not -len(self) <= k < len(self):
            raise IndexError(f"sweep {k} out of range for {len(self)} sweeps")
        return self.events.time_window(int(self.start_us[k]), int(self.stop_us[k]))

    def __iter__(self) -> Iterator[EventStream]:
        for k in range(len(self)):
            yield self[k]

    def sweep_index(self) -> np.ndarray:
        """Per event, the index of its sweep, or -1 for events in no sweep (int64)."""
        t = self.events.t_us
        k = np.searchsorted(self.start_us, t, side="right") - 1
        inside = (
            (k >= 0) & (t < self.stop_us[np.clip(k, 0, None)]) if k.size else k >= 0
        )
        return np.where(inside, k, -1)

    def time_in_sweep_us(self) -> np.ndarray:
        """Per event, µs since its sweep's start (-1 for events in no sweep)."""
        k = self.sweep_index()
        return np.where(
            k >= 0, self.events.t_us - self.start_us[np.clip(k, 0, None)], -1
        )


def estimate_sweep_phase(
    t_us: np.ndarray, period_us: float | int, *, bins: int = 2048
) -> float:
    """The phase in `[0, period_us)` where the folded event density is lowest.

    The event times folded modulo the period are histogrammed (`bins` bins), smoothed
    with a circular box of 1/64 period, and the centre of the longest circular run of
    bins within 2 % (of the mean-minus-minimum span) of the minimum is returned.

    **Arguments:**

    - `t_us`: event times, shape `(ev,)`, µs.
    - `period_us`: sweep period in µs (> 0; need not be an integer).
    - `bins`: histogram bins over one period.

    **Returns:** the phase in µs (a float).
    """
    if not period_us > 0:
        raise ValueError(f"period_us must be positive, got {period_us}")
    if t_us.size == 0:
        return 0.0
    bins = int(max(8, min(bins, int(np.ceil(period_us)))))
    ref = int(t_us[0]) - int(t_us[0]) % max(1, int(period_us))
    folded = np.mod((t_us - ref).astype(np.float64), period_us)
    hist = np.bincount(
        np.minimum((folded * (bins / period_us)).astype(np.int64), bins - 1),
        minlength=bins,
    ).astype(np.float64)
    width = max(1, bins // 64)
    kernel = np.ones(width) / width
    smooth = np.convolve(np.concatenate([hist[-width:], hist, hist[:width]]), kernel)
    smooth = smooth[width + (width - 1) // 2 : width + (width - 1) // 2 + bins]
    low = smooth.min()
    quiet = smooth <= low + 0.02 * (smooth.mean() - low)
    if quiet.all():
        centre = 0.0
    else:
        # Longest circular run of quiet bins: rotate so the run cannot wrap.
        shift = int(np.flatnonzero(~quiet)[0])
        q = np.roll(quiet, -shift)
        edges = np.diff(np.concatenate([[0], q.astype(np.int8), [0]]))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        longest = int(np.argmax(stops - starts))
        centre = (starts[longest] + stops[longest]) / 2 + shift
    return float(np.mod(ref + centre * period_us / bins, period_us))


def split_sweeps(
    events: EventStream,
    *,
    period_us: float | int | None = None,
    triggers: str = "auto",
    trigger_id: int = 0,
    trigger_p: int = 1,
    phase_us: float | int | None = None,
) -> Sweeps:
    """Split a stream into sweeps, from encoder triggers or a nominal period.

    **Arguments:**

    - `events`: a time-ordered stream.
    - `period_us`: nominal sweep period in µs (e.g. `1e6 / sweep_rate_hz`); required
      without triggers, and ends the last sweep when there is a single trigger.
    - `triggers`: `"auto"` (use triggers when the stream has matching ones, else the
      period), `"require"` (error without triggers) or `"ignore"` (period only).
    - `trigger_id`, `trigger_p`: which trigger events mark sweep starts (channel 0,
      rising edge by default; see the module doc).
    - `phase_us`: the period path's phase; estimated from the data when `None`.

    **Returns:** a `Sweeps`.
    """
    if triggers not in ("auto", "require", "ignore"):
        raise ValueError(
            f"triggers must be 'auto', 'require' or 'ignore', not {triggers!r}"
        )
    if period_us is not None and not period_us > 0:
        raise ValueError(f"period_us must be positive, got {period_us}")
    if not events.is_time_ordered():
        raise ValueError("split_sweeps needs a time-ordered stream")
    marks = np.unique(_trigger_marks(events, trigger_id, trigger_p))
    usable = marks.size >= 2 or (marks.size == 1 and period_us is not None)
    if triggers == "require" and not usable:
        raise ValueError(
            f"stream has {marks.size} sweep triggers (id {trigger_id}, edge "
            f"{trigger_p}); need 2, or 1 and period_us"
        )
    if triggers != "ignore" and usable:
        period = (
            float(np.median(np.diff(marks))) if marks.size >= 2 else float(period_us)
        )
        stops = np.append(marks[1:], _last_stop(marks, period))
        return Sweeps(
            start_us=marks.astype(np.int64),
            stop_us=stops.astype(np.int64),
            source="trigger",
            period_us=period,
            phase_us=float(np.mod(marks[0], period)),
            events=events,
        )
    if period_us is None:
        raise ValueError(
            "stream has no sweep triggers: pass period_us (sweep period, µs)"
        )
    period = float(period_us)
    t = events.t_us
    if phase_us is None:
        phase_us = estimate_sweep_phase(t, period)
    if t.size == 0:
        empty = np.zeros(0, np.int64)
        return Sweeps(empty, empty, "period", period, float(phase_us), events)
    k0 = int(np.floor((int(t[0]) - phase_us) / period))
    k1 = int(np.floor((int(t[-1]) - phase_us) / period))
    cuts = _period_cut(phase_us, period, np.arange(k0, k1 + 2))
    # Rounding may put an event just outside the first/last cut: widen by one period.
    if cuts[0] > t[0]:
        cuts = np.concatenate([[cuts[0] - int(round(period))], cuts])
    if cuts[-1] <= t[-1]:
        cuts = np.append(cuts, cuts[-1] + int(round(period)))
    return Sweeps(
        start_us=cuts[:-1],
        stop_us=cuts[1:],
        source="period",
        period_us=period,
        phase_us=float(np.mod(phase_us, period)),
        events=events,
    )


class SweepCutter:
    """Cuts a chunked, time-ordered event stream into sweeps with bounded memory: the
    streaming form of :func:`split_sweeps`, with the same boundary rules
    (:func:`_trigger_marks`, :func:`_last_stop`, :func:`_period_cut`).

    Sweep starts come from encoder triggers (id `trigger_id`, rising edge) or, without
    any in the first few periods, at `phase_us + j period_us` (the band's own sweep
    starts, as `reconstruct`'s `t_start_us`: the reconstruction needs each sweep's
    time origin, not just a cut in the dead time; `phase_us=None` is 0 here, where
    `split_sweeps` estimates a cut in the dead time).
    Yields `(k, start, stop, events, before)`:
    `events` holds the sweep's events, `before` the events that precede the first
    sweep (they set pixel references, nothing else).
    """

    def __init__(self, chunks, period_us, triggers, phase_us, trigger_id=0):
        self.chunks = iter(chunks)
        self.period = float(period_us)
        self.mode = triggers
        self.phase = phase_us
        self.trigger_id = trigger_id
        self.pending: list[EventStream] = []
        self.marks: list[int] = []
        self.t_max = -(2**62)
        self.exhausted = False
        self.geometry = None

    def _pull(self) -> bool:
        try:
            c = next(self.chunks)
        except StopIteration:
            self.exhausted = True
            return False
        self.geometry = (c.width, c.height)
        for m in _trigger_marks(c, self.trigger_id).tolist():
            if not self.marks or m > self.marks[-1]:
                self.marks.append(int(m))
        if len(c):
            self.pending.append(c)
            self.t_max = max(self.t_max, int(c.t_us[-1]))
        return True

    def _take(self, t0: int, t1: int) -> EventStream:
        """Events in `[t0, t1)`; everything before `t1` leaves the buffer."""
        w, h = self.geometry
        if not self.pending:
            return EventStream(*(np.zeros(0, np.int64),) * 4, w, h)
        cat = EventStream.concatenate(self.pending) if len(self.pending) > 1 else None
        cat = cat or self.pending[0]
        out = cat.time_window(t0, t1)
        rest = cat.time_window(t1, 2**62)
        self.pending = [rest] if len(rest) else []
        return out

    def _decide(self):
        """Trigger or period mode, from the first ~4 periods of data."""
        while not self.exhausted and (
            not self.pending
            or self.t_max - int(self.pending[0].t_us[0]) < 4 * self.period
        ):
            self._pull()
        use_trig = self.mode != "ignore" and len(self.marks) >= 1
        if self.mode == "require" and not use_trig:
            raise ValueError(
                f"no sweep triggers (id {self.trigger_id}, rising edge) in the first "
                "periods of the recording"
            )
        self.mode = "trigger" if use_trig else "period"
        if self.mode == "period" and self.phase is None:
            self.phase = 0.0

    def __iter__(self):
        self._decide()
        if self.geometry is None:
            return
        if self.mode == "trigger":
            yield from self._by_trigger()
        else:
            yield from self._by_period()

    def _by_trigger(self):
        first = self.marks[0]
        before = self._take(-(2**62), first)
        k = 0
        while True:
            while len(self.marks) < k + 2 and not self.exhausted:
                self._pull()
            if len(self.marks) >= k + 2:
                start, stop = self.marks[k], self.marks[k + 1]
                while self.t_max < stop and not self.exhausted:
                    self._pull()
            else:  # the last sweep: one median interval (or period) long
                start = self.marks[k]
                stop = _last_stop(np.asarray(self.marks), self.period)
                while not self.exhausted:
                    self._pull()
            yield k, start, stop, self._take(start, stop), before
            before = None
            k += 1
            if len(self.marks) < k + 1:
                return

    def _by_period(self):
        if not self.pending:
            return
        t0 = int(self.pending[0].t_us[0])
        j0 = math.floor((t0 - self.phase) / self.period)

        def cut(j):
            return int(_period_cut(self.phase, self.period, j))

        if cut(j0) > t0:
            j0 -= 1
        k = 0
        while True:
            start, stop = cut(j0 + k), cut(j0 + k + 1)
            while self.t_max < stop and not self.exhausted:
                self._pull()
            if not self.pending and self.exhausted:
                return
            yield k, start, stop, self._take(start, stop), None
            k += 1
