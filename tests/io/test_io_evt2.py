"""EVT 2.0 reading: the real recording, generated files, defects."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._io import EventReader, describe_events, read_events

DATA = Path(
    os.environ.get("EVHSI_SHARED_DATA", Path(__file__).parents[3] / "shared" / "data")
)
SAMPLE = DATA / "evt2_sample.raw"
HEADER = b"% evt 2.0\n% format EVT2;height=480;width=640\n% end\n"


# Every test here runs with the compiled kernels and with the NumPy reference.
pytestmark = pytest.mark.usefixtures("io_backend")


def evt2_words(ev: EventStream, start_us: int = 0) -> np.ndarray:
    """An independent, loop-based EVT 2.0 encoder (reference for the reader).

    Like a sensor, it states the time base at `start_us` first: a stream that began
    after a 34-bit wrap could not tell its absolute time otherwise."""
    items = [
        (int(t), 1, (int(x), int(y), int(p)))
        for x, y, p, t in zip(ev.x, ev.y, ev.p, ev.t_us)
    ]
    items += [
        (int(t), 0, (int(p), int(i)))
        for t, p, i in zip(ev.trigger_t_us, ev.trigger_p, ev.trigger_id)
    ]
    items.sort(key=lambda it: (it[0], it[1]))
    out, high = [(0x8 << 28) | ((start_us >> 6) & 0x0FFFFFFF)], start_us >> 6
    for t, kind, data in items:
        if (t >> 6) != high:
            high = t >> 6
            out.append((0x8 << 28) | (high & 0x0FFFFFFF))
        low = (t & 0x3F) << 22
        if kind:
            x, y, p = data
            out.append((p << 28) | low | (x << 11) | y)
        else:
            p, i = data
            out.append((0xA << 28) | low | (i << 8) | p)
    return np.array(out, "<u4")


def write_evt2(path: Path, ev: EventStream, start_us: int = 0) -> Path:
    path.write_bytes(HEADER + evt2_words(ev, start_us).tobytes())
    return path


def random_stream(
    seed: int, n: int, span: int, triggers: int = 0, t0: int = 0
) -> EventStream:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + span + 1, n))
    gt = np.sort(rng.integers(t0, t0 + span + 1, triggers))
    return EventStream(
        rng.integers(0, 640, n),
        rng.integers(0, 480, n),
        rng.integers(0, 2, n),
        t,
        640,
        480,
        trigger_t_us=gt,
        trigger_p=rng.integers(0, 2, triggers),
        trigger_id=rng.integers(0, 32, triggers),
    )


@pytest.mark.skipif(not SAMPLE.is_file(), reason="shared data absent")
def test_real_evt2_sample_is_plausible():
    reader = EventReader(SAMPLE, strict=True)
    ev = reader.read()
    assert reader.format == "evt2" and reader.report.clean
    assert len(ev) > 100_000
    assert ev.is_time_ordered()
    assert int(ev.x.max()) < ev.width and int(ev.y.max()) < ev.height
    assert 0.1 < float(ev.p.mean()) < 0.9  # both polarities
    duration_s = ev.duration_us * 1e-6
    assert 1e-3 < duration_s < 60
    assert 1e3 < len(ev) / duration_s < 1e9  # events per second
    expelliarmus = pytest.importorskip("expelliarmus")
    ref = expelliarmus.Wizard(encoding="evt2").read(SAMPLE)
    np.testing.assert_array_equal(ev.x, ref["x"])
    np.testing.assert_array_equal(ev.y, ref["y"])
    np.testing.assert_array_equal(ev.p, ref["p"])
    np.testing.assert_array_equal(ev.t_us, ref["t"])
    info = describe_events(SAMPLE)
    assert info["format"] == "evt2" and info["events"] == len(ev)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 200),
    span=st.sampled_from([0, 63, 100_000]),
    t0=st.sampled_from([0, 2**34 - 5_000]),  # the second crosses a 34-bit wrap
    triggers=st.integers(0, 4),
    chunk_bytes=st.sampled_from([3, 7, 4096]),
)
def test_evt2_generated_roundtrip(
    tmp_path_factory, seed, n, span, t0, triggers, chunk_bytes
):
    ev = random_stream(seed, n, span, triggers, t0)
    path = write_evt2(tmp_path_factory.mktemp("e2") / "a.raw", ev, t0)
    reader = EventReader(path, strict=True, chunk_bytes=chunk_bytes)
    got = EventStream.concatenate(list(reader)) if n or triggers else reader.read()
    assert (got.width, got.height) == (640, 480)
    for k in ("x", "y", "p", "t_us", "trigger_t_us", "trigger_p", "trigger_id"):
        np.testing.assert_array_equal(getattr(got, k), getattr(ev, k), err_msg=k)


def test_evt2_defects(tmp_path):
    ev = random_stream(1, 20, 1000)
    words = evt2_words(ev)
    bad = np.concatenate(
        [words[:5], np.array([0x3 << 28, 0x2 << 28], "<u4"), words[5:]]
    )
    path = tmp_path / "bad.raw"
    path.write_bytes(HEADER + bad.tobytes() + b"\x01\x02")
    reader = EventReader(path)
    got = reader.read()
    np.testing.assert_array_equal(got.t_us, ev.t_us)
    assert reader.report.unknown_words == 2 and reader.report.trailing_bytes == 2
    with pytest.raises(ValueError, match="reserved word type 0x3"):
        read_events(path, strict=True)
    # CD events before the first TIME_HIGH, and outside the geometry.
    orphan = np.array([(1 << 28) | (5 << 11) | 6], "<u4")
    outside = np.array([(0x8 << 28) | 1, (1 << 28) | (700 << 11) | 6], "<u4")
    path.write_bytes(HEADER + np.concatenate([orphan, words, outside]).tobytes())
    reader = EventReader(path)
    assert len(reader.read()) == 20
    assert reader.report.events_before_time == 1 and reader.report.out_of_geometry == 1
    with pytest.raises(ValueError, match="before the first TIME_HIGH"):
        read_events(path, strict=True)
