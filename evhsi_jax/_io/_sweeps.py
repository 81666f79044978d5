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
from collections.abc import Iterator

import numpy as np

from .._events import EventStream

__all__ = ["Sweeps", "split_sweeps", "estimate_sweep_phase"]


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
    sel = (events.trigger_id == trigger_id) & (events.trigger_p == trigger_p)
    marks = np.unique(events.trigger_t_us[sel])
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
        stops = np.append(marks[1:], marks[-1] + int(round(period)))
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
    cuts = np.round(phase_us + period * np.arange(k0, k1 + 2)).astype(np.int64)
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
