"""Bandwidth accounting: EVT 3.0 bytes agree with the writer; nominal and frame bytes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._io import (
    EventReader,
    bandwidth_summary,
    evt3_bytes,
    frame_bytes,
    nominal_event_bytes,
    write_evt3,
)

# Every test here runs with the compiled kernels and with the NumPy reference.
pytestmark = pytest.mark.usefixtures("io_backend")


def stream(seed: int, n: int, span: int, triggers: int = 0) -> EventStream:
    rng = np.random.default_rng(seed)
    return EventStream(
        rng.integers(0, 320, n),
        rng.integers(0, 240, n),
        rng.integers(0, 2, n),
        np.sort(rng.integers(0, span + 1, n)),
        320,
        240,
        trigger_t_us=np.sort(rng.integers(0, span + 1, triggers)),
        trigger_p=np.ones(triggers, np.int64),
        trigger_id=np.zeros(triggers, np.int64),
    )


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 500),
    span=st.sampled_from([0, 10, 10_000, 60_000_000]),
    triggers=st.integers(0, 3),
    reorder=st.booleans(),
)
def test_evt3_bytes_is_the_file_size(
    tmp_path_factory, seed, n, span, triggers, reorder
):
    ev = stream(seed, n, span, triggers)
    path = tmp_path_factory.mktemp("bw") / "a.raw"
    write_evt3(path, ev, reorder=reorder)
    size = path.stat().st_size
    assert evt3_bytes(ev, reorder=reorder, header=True) == size
    assert evt3_bytes(ev, reorder=reorder) == size - EventReader(path).header.size


def test_layouts_cost_what_the_format_says():
    n = 720
    # A column sweep: one event per row at each µs step needs a row word, a column
    # word and a TIME_LOW word per event (3 words = 48 bits).
    col = EventStream(
        np.full(n, 5), np.arange(n), np.ones(n), np.arange(n) * 7, 1280, 720
    )
    assert 8 * evt3_bytes(col) / n == pytest.approx(48, abs=0.5)
    # The same events in one µs share the time words: 2 words per event.
    col_same_t = EventStream(col.x, col.y, col.p, np.full(n, 9), 1280, 720)
    assert 8 * evt3_bytes(col_same_t) / n == pytest.approx(32, abs=0.5)
    # A full row in one µs is vectorised: about 1.4 bits per event.
    row = EventStream(
        np.arange(1280), np.full(1280, 3), np.ones(1280), np.full(1280, 9), 1280, 720
    )
    assert 8 * evt3_bytes(row) / 1280 < 2
    # Reordering a shuffled µs recovers the vectors.
    rng = np.random.default_rng(0)
    shuffled = row.take(rng.permutation(1280))
    assert evt3_bytes(shuffled, reorder=True) == evt3_bytes(row)
    assert evt3_bytes(shuffled) > 10 * evt3_bytes(row)


def test_nominal_and_frames():
    assert nominal_event_bytes(1000) == 2000.0
    assert nominal_event_bytes(np.int64(3), 12) == 4.5
    assert frame_bytes(72, 1280, 720) == 72 * 1280 * 720
    assert frame_bytes(2, 10, 10, bits_per_pixel=12) == 300.0
    with pytest.raises(ValueError):
        nominal_event_bytes(-1)
    with pytest.raises(ValueError):
        frame_bytes(1, 0, 10)


def test_bandwidth_summary():
    ev = stream(4, 2000, 50_000)
    out = bandwidth_summary(ev, frames=3)
    assert out["events"] == 2000 and out["evt3_bytes"] == evt3_bytes(ev)
    assert out["evt3_bytes_reordered"] == evt3_bytes(ev, reorder=True)
    assert out["nominal16_bytes"] == 4000.0
    assert out["frame_bytes"] == 3 * 320 * 240
    assert out["evt3_over_frames"] == pytest.approx(out["evt3_bytes"] / (3 * 320 * 240))
    assert out["evt3_bits_per_event"] == pytest.approx(8 * out["evt3_bytes"] / 2000)
    assert "frame_bytes" not in bandwidth_summary(ev)
