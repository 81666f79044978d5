"""Sweep segmentation: from encoder triggers, or from a period and an estimated phase."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._io import Sweeps, estimate_sweep_phase, split_sweeps


def swept(
    seed: int,
    sweeps: int,
    period_us: float,
    *,
    busy: float = 0.7,
    offset: float = 0.1,
    triggers: bool = True,
    noise_triggers: bool = True,
):
    """Each sweep k fires events in [k·P + offset·P, k·P + (offset+busy)·P), quiet
    otherwise; the encoder marks k·P (id 0, rising). Returns the stream and each
    event's sweep."""
    rng = np.random.default_rng(seed)
    per = rng.integers(50, 200, sweeps)
    label = np.repeat(np.arange(sweeps), per)
    start = np.round(np.arange(sweeps) * period_us).astype(np.int64)
    phase = rng.uniform(offset, offset + busy, label.size) * period_us
    t = start[label] + phase.astype(np.int64)
    order = np.argsort(t, kind="stable")
    t, label = t[order], label[order]
    n = t.size
    trig_t = start if triggers else np.zeros(0, np.int64)
    trig_p = np.ones(trig_t.size, np.int64)
    trig_id = np.zeros(trig_t.size, np.int64)
    if triggers and noise_triggers:  # falling edges and another channel: ignored
        extra = start + int(period_us / 2)
        trig_t = np.concatenate([trig_t, extra, extra + 1])
        trig_p = np.concatenate(
            [trig_p, np.zeros(sweeps, np.int64), np.ones(sweeps, np.int64)]
        )
        trig_id = np.concatenate(
            [trig_id, np.zeros(sweeps, np.int64), np.full(sweeps, 2)]
        )
        o = np.argsort(trig_t, kind="stable")
        trig_t, trig_p, trig_id = trig_t[o], trig_p[o], trig_id[o]
    ev = EventStream(
        rng.integers(0, 64, n),
        rng.integers(0, 48, n),
        rng.integers(0, 2, n),
        t,
        64,
        48,
        trigger_t_us=trig_t,
        trigger_p=trig_p,
        trigger_id=trig_id,
    )
    return ev, label


def test_sweeps_from_triggers():
    period = 1e6 / 30
    ev, label = swept(0, 6, period)
    sw = split_sweeps(ev)
    assert isinstance(sw, Sweeps) and sw.source == "trigger" and len(sw) == 6
    np.testing.assert_array_equal(sw.start_us, np.round(np.arange(6) * period))
    assert sw.period_us == pytest.approx(period, abs=1)
    assert np.all(sw.stop_us[:-1] == sw.start_us[1:])
    np.testing.assert_array_equal(sw.sweep_index(), label)
    for k, part in enumerate(sw):
        assert len(part) == int(np.sum(label == k))
        assert part.trigger_t_us[0] == sw.start_us[k]  # its own start trigger
    dt = sw.time_in_sweep_us()
    assert dt.min() >= 0 and dt.max() < period


def test_trigger_edge_cases():
    period = 10_000.0
    ev, label = swept(1, 3, period)
    # Events before the first sweep trigger belong to no sweep.
    late = EventStream.concatenate(
        [
            ev,
            EventStream(
                np.array([1]), np.array([1]), np.array([1]), np.array([-50]), 64, 48
            ),
        ]
    )
    idx = split_sweeps(late).sweep_index()
    assert idx[0] == -1 and np.array_equal(idx[1:], label)
    # A single trigger needs the period to end its sweep.
    one = EventStream(
        ev.x,
        ev.y,
        ev.p,
        ev.t_us,
        64,
        48,
        trigger_t_us=np.array([0]),
        trigger_p=np.array([1]),
        trigger_id=np.array([0]),
    )
    sw = split_sweeps(one, period_us=period)
    assert (len(sw), int(sw.stop_us[0])) == (1, 10_000)
    with pytest.raises(ValueError, match="no sweep triggers"):
        split_sweeps(one)  # one trigger, no period: falls back, then fails
    with pytest.raises(ValueError, match="need 2"):
        split_sweeps(one, triggers="require")
    # Other channel / edge conventions are selectable.
    sw = split_sweeps(ev, trigger_id=2)
    assert sw.source == "trigger" and len(sw) == 3
    np.testing.assert_array_equal(sw.start_us, np.round(np.arange(3) * period) + 5001)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    period=st.floats(2_000, 100_000),
    offset=st.floats(0.0, 0.9),
    busy=st.floats(0.3, 0.8),
    t0_sweeps=st.integers(0, 10**6),
)
def test_sweeps_from_period_find_the_gap(seed, period, offset, busy, t0_sweeps):
    ev, label = swept(seed, 5, period, busy=busy, offset=offset, triggers=False)
    shift = int(round(t0_sweeps * period))  # an arbitrary absolute start
    ev = EventStream(ev.x, ev.y, ev.p, ev.t_us + shift, 64, 48)
    sw = split_sweeps(ev, period_us=period)
    assert sw.source == "period"
    idx = sw.sweep_index()
    assert np.all(idx >= 0)
    # Every sweep's events land together in one segment, in order, none split.
    segments = idx - idx[0]
    np.testing.assert_array_equal(segments, label - label[0])
    # The cut is inside the quiet gap (folded modulo the period).
    busy_lo = (offset * period) % period
    cut = (sw.phase_us - shift) % period
    into = (cut - busy_lo) % period
    assert into >= busy * period - 2 * period / 64 - 1


def test_period_path_options_and_errors():
    ev, _ = swept(3, 4, 20_000.0, triggers=False)
    with pytest.raises(ValueError, match="pass period_us"):
        split_sweeps(ev)
    with pytest.raises(ValueError, match="triggers must be"):
        split_sweeps(ev, period_us=20_000, triggers="maybe")
    with pytest.raises(ValueError, match="positive"):
        split_sweeps(ev, period_us=0)
    sw = split_sweeps(ev, period_us=20_000, phase_us=0)
    np.testing.assert_array_equal(sw.start_us, np.arange(4) * 20_000)
    trig, _ = swept(3, 4, 20_000.0)
    assert split_sweeps(trig, period_us=20_000, triggers="ignore").source == "period"
    empty = EventStream(*(np.zeros(0, np.int64),) * 4, 64, 48)
    assert len(split_sweeps(empty, period_us=1000)) == 0
    backwards = EventStream(*(np.array([1, 1]),) * 3, np.array([5, 1]), 64, 48)
    with pytest.raises(ValueError, match="time-ordered"):
        split_sweeps(backwards, period_us=1000)
    with pytest.raises(IndexError):
        sw[4]


def test_estimate_phase_reference():
    # Events uniform on [0.2, 0.6) of each period: the quiet stretch is [0.6, 1.2).
    period = 1000.0
    rng = np.random.default_rng(0)
    t = np.sort((rng.integers(0, 50, 20_000) + rng.uniform(0.2, 0.6, 20_000)) * period)
    phase = estimate_sweep_phase(t.astype(np.int64), period)
    assert phase == pytest.approx(900.0, abs=20)  # the middle of the gap
