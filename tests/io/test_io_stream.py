"""Streaming reads: chunked decode equals whole-file decode, time windows, memory."""

from __future__ import annotations

import os
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._io import (
    EventReader,
    iter_events,
    read_events,
    read_events_window,
    write_events,
    write_evt3,
)

DATA = Path(
    os.environ.get("EVHSI_SHARED_DATA", Path(__file__).parents[3] / "shared" / "data")
)
COLUMNS = ("x", "y", "p", "t_us", "trigger_t_us", "trigger_p", "trigger_id")


# Every test here runs with the compiled kernels and with the NumPy reference.
pytestmark = pytest.mark.usefixtures("io_backend")


def bursts(seed: int, n_bursts: int, *, gap_us: int = 3, triggers: int = 0):
    """Rows of neighbouring columns firing together (vector words), time steps and
    occasional long gaps (24-bit wraps), triggers interleaved."""
    rng = np.random.default_rng(seed)
    length = rng.integers(1, 30, n_bursts)
    t_b = np.cumsum(rng.integers(0, gap_us, n_bursts)) + 10
    t_b += np.cumsum(rng.random(n_bursts) < 0.002) * 20_000_000  # wraps
    y_b = rng.integers(0, 720, n_bursts)
    p_b = rng.integers(0, 2, n_bursts)
    x_b = rng.integers(0, 1280 - 30, n_bursts)
    b = np.repeat(np.arange(n_bursts), length)
    off = np.arange(b.size) - np.repeat(np.cumsum(length) - length, length)
    keep = rng.random(b.size) < 0.8
    b, off = b[keep], off[keep]
    gt = np.sort(rng.choice(t_b, triggers)) if triggers else np.zeros(0, np.int64)
    return EventStream(
        x_b[b] + off,
        y_b[b],
        p_b[b],
        t_b[b],
        1280,
        720,
        trigger_t_us=gt,
        trigger_p=rng.integers(0, 2, gt.size),
        trigger_id=rng.integers(0, 16, gt.size),
    )


def assert_same(a: EventStream, b: EventStream) -> None:
    for k in COLUMNS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


@pytest.fixture(scope="module")
def sample_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("stream") / "bursts.raw"
    write_evt3(path, bursts(7, 1500, triggers=40))
    return path


def chunked(path: Path, chunk_bytes: int, workers: int | None = None) -> EventStream:
    reader = EventReader(path, chunk_bytes=chunk_bytes, workers=workers)
    parts = list(reader)
    assert all(len(c) or c.trigger_t_us.size for c in parts)
    return EventStream.concatenate(parts) if parts else read_events(path)


@pytest.mark.parametrize(
    "chunk_bytes", [1, 2, 3, 5, 64, 77, 1000, 4096, 65537, 1 << 20]
)
def test_chunked_equals_whole(sample_file, chunk_bytes):
    whole = read_events(sample_file)
    assert_same(whole, chunked(sample_file, chunk_bytes))


@pytest.mark.parametrize("chunk_bytes", [64, 1001, 4096])
def test_parallel_decode_equals_serial(sample_file, chunk_bytes):
    serial = EventReader(sample_file, chunk_bytes=chunk_bytes, workers=1)
    parallel = EventReader(sample_file, chunk_bytes=chunk_bytes, workers=2)
    assert_same(serial.read(), parallel.read())
    assert serial.report == parallel.report
    assert_same(serial.read(), chunked(sample_file, chunk_bytes, workers=2))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), chunk_bytes=st.integers(1, 5000))
def test_chunked_equals_whole_random(tmp_path_factory, seed, chunk_bytes):
    path = tmp_path_factory.mktemp("s") / "r.raw"
    write_evt3(path, bursts(seed, 60, triggers=3))
    assert_same(read_events(path), chunked(path, chunk_bytes))


def test_chunk_boundaries_inside_vector_sequences(tmp_path):
    # One row of 24 events: VECT_BASE_X, VECT_12, VECT_12. Cut after every word.
    x = np.arange(100, 124)
    ev = EventStream(x, np.full(24, 5), np.ones(24), np.full(24, 9000), 1280, 720)
    write_evt3(tmp_path / "v.raw", ev)
    for cb in (2, 4, 6, 8):
        assert_same(ev, chunked(tmp_path / "v.raw", cb))


@pytest.mark.skipif(not (DATA / "evt3_sample.raw").is_file(), reason="no shared data")
@pytest.mark.parametrize("chunk_bytes", [999, 4096, 100_001])
def test_real_sample_chunked(chunk_bytes):
    path = DATA / "evt3_sample.raw"
    assert_same(read_events(path), chunked(path, chunk_bytes))


def test_iter_events_and_npz(tmp_path, sample_file):
    whole = read_events(sample_file)
    parts = list(iter_events(sample_file, chunk_bytes=1000))
    assert len(parts) > 5
    assert_same(whole, EventStream.concatenate(parts))
    write_events(tmp_path / "w.npz", whole)
    parts = list(iter_events(tmp_path / "w.npz", chunk_bytes=5000))
    assert len(parts) > 5
    assert_same(whole, EventStream.concatenate(parts))


def window_cases(ev: EventStream):
    t = ev.t_us.tolist()
    yield t[0], t[-1] + 1
    yield t[0] - 100, t[0]
    yield t[len(t) // 3], t[len(t) // 2]
    yield t[len(t) // 2], t[len(t) // 2]
    yield t[-1], t[-1] + 10**9
    yield t[5] + 1, t[-5] - 1
    yield 2**24 - 10, 2**24 + 40_000_000


@pytest.mark.parametrize("chunk_bytes, workers", [(37, 1), (4096, 2), (1 << 19, None)])
def test_time_window_equals_filter(sample_file, chunk_bytes, workers):
    whole = read_events(sample_file)
    reader = EventReader(sample_file, chunk_bytes=chunk_bytes, workers=workers)
    for t0, t1 in window_cases(whole):
        assert_same(whole.time_window(t0, t1), reader.read_window(t0, t1))
    t0, t1 = int(whole.t_us[100]), int(whole.t_us[200])
    assert_same(whole.time_window(t0, t1), read_events_window(sample_file, t0, t1))


def test_time_window_decodes_only_overlapping_chunks(sample_file):
    reader = EventReader(sample_file, chunk_bytes=4096)
    whole = read_events(sample_file)
    t0 = int(whole.t_us[len(whole) // 2])
    part = reader.read_window(t0, t0 + 5)
    assert len(part) > 0
    assert reader.report.words * 2 < 3 * 4096 + 4096  # a chunk or two, not the file


def test_streaming_memory_is_bounded(tmp_path):
    ev = bursts(3, 200_000)  # ~2.4 M events (31 MB decoded), ~1.9 MB of EVT 3.0
    path = tmp_path / "big.raw"
    write_evt3(path, ev)
    n, size = len(ev), path.stat().st_size
    del ev
    tracemalloc.start()
    try:
        count = 0
        for chunk in iter_events(path, chunk_bytes=16 * 1024):
            count += len(chunk)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == n
    # A decoded event takes 13 bytes (x, y, p, t); the whole decode would need n * 13.
    assert peak < n * 13 / 10, (peak, n * 13, size)
