"""EVT 3.0 files: conformance on a real recording, round trips, peers, errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._io import (
    DecodeError,
    EventReader,
    _evt3_encode,
    describe_events,
    encode_evt3_words,
    evt3_word_count,
    parse_header,
    read_events,
    write_events,
    write_evt3,
)

DATA = Path(
    os.environ.get("EVHSI_SHARED_DATA", Path(__file__).parents[3] / "shared" / "data")
)
SAMPLE = DATA / "evt3_sample.raw"
needs_sample = pytest.mark.skipif(not SAMPLE.is_file(), reason="shared data absent")
FAST = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
COLUMNS = ("x", "y", "p", "t_us", "trigger_t_us", "trigger_p", "trigger_id")


# Every test here runs with the compiled kernels and with the NumPy reference.
pytestmark = pytest.mark.usefixtures("io_backend")


def random_stream(
    seed: int,
    n: int,
    *,
    width: int = 1280,
    height: int = 720,
    t0: int = 0,
    span: int = 10_000,
    clustered: bool = True,
    triggers: int = 0,
) -> EventStream:
    """Time-ordered events; `clustered` puts runs of columns in one row and µs."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + span + 1, n))
    x = rng.integers(0, width, n)
    y = rng.integers(0, height, n)
    p = rng.integers(0, 2, n)
    if clustered and n > 1:
        # Runs: copy time, row and polarity forward and step the column by 1..3.
        run = rng.random(n) < 0.7
        run[0] = False
        start = np.maximum.accumulate(np.where(run, 0, np.arange(n)))
        t, y, p = t[start], y[start], p[start]
        step = np.cumsum(rng.integers(1, 4, n))
        x = np.minimum(x[start] + step - step[start], width - 1)
    gt = np.sort(rng.integers(t0, t0 + span + 1, triggers))
    return EventStream(
        x,
        y,
        p,
        t,
        width,
        height,
        trigger_t_us=gt,
        trigger_p=rng.integers(0, 2, triggers),
        trigger_id=rng.integers(0, 16, triggers),
    )


def mk(x, y, p, t, width: int, height: int, **triggers) -> EventStream:
    """An `EventStream` from lists (the type-checked constructor wants arrays)."""
    arrays = {k: np.asarray(v, np.int64) for k, v in triggers.items()}
    return EventStream(
        *(np.asarray(v, np.int64) for v in (x, y, p, t)), width, height, **arrays
    )


def assert_same(a: EventStream, b: EventStream) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    for k in COLUMNS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


def roundtrip(tmp_path: Path, ev: EventStream, **kw) -> EventStream:
    path = tmp_path / "rt.raw"
    write_evt3(path, ev, **kw)
    return read_events(path, strict=True)


# --- the real recording ---
@needs_sample
def test_real_sample_xyp_exact():
    ev = read_events(SAMPLE)
    ref = np.load(DATA / "evt3_sample_xyp.npy").astype(np.int64)
    assert len(ev) == 219_596 == ref.shape[0]
    np.testing.assert_array_equal(ev.x, ref[:, 0])
    np.testing.assert_array_equal(ev.y, ref[:, 1])
    np.testing.assert_array_equal(ev.p, ref[:, 2])
    assert ev.is_time_ordered()
    assert 7_500 <= ev.duration_us <= 10_500
    assert (ev.width, ev.height) == (1280, 720)


@needs_sample
def test_real_sample_times_match_evt3_and_report():
    evt3 = pytest.importorskip("evt3")
    reader = EventReader(SAMPLE, strict=True)
    ev = reader.read()
    ref = evt3.decode_file(str(SAMPLE))
    np.testing.assert_array_equal(ev.t_us, ref.t.astype(np.int64))
    assert reader.report.clean and reader.report.events == len(ev)
    assert reader.geometry_source == "default"  # the header states no geometry
    assert reader.header is not None and not reader.header.has_end


@needs_sample
def test_real_sample_rewrite_is_smaller_and_identical(tmp_path):
    ev = read_events(SAMPLE)
    back = roundtrip(tmp_path, ev)
    assert_same(ev, back)
    assert (tmp_path / "rt.raw").stat().st_size < SAMPLE.stat().st_size


@needs_sample
def test_describe_real_sample():
    info = describe_events(SAMPLE)
    assert info["format"] == "evt3" and info["events"] == 219_596
    assert info["width"] == 1280 and info["height"] == 720
    assert 7_500 <= info["duration_us"] <= 10_500
    assert 0.0 < info["on_fraction"] < 1.0 and info["triggers"] == 0
    assert info["bytes_per_event"] == pytest.approx(SAMPLE.stat().st_size / 219_596)
    assert info["rate_ev_per_s"] == pytest.approx(
        219_596 / (info["duration_us"] * 1e-6)
    )


# --- headers ---
@pytest.mark.parametrize(
    "text, fmt, geometry",
    [
        ("% evt 3.0\n% end\n", "evt3", None),
        ("% format EVT3;height=480;width=640\n", "evt3", (640, 480)),
        ("% evt 3.0\n% geometry 2048x1536\n% end\n", "evt3", (2048, 1536)),
        ("% evt 2.0\n% Width 304\n% Height 240\n", "evt2", (304, 240)),
        ("% format EVT2\n% end\n", "evt2", None),
        ("% Date 2020\n% plugin_name x\n", None, None),
    ],
)
def test_parse_header(text, fmt, geometry):
    data = text.encode() + bytes([0x2D, 0x8B, 0x00, 0x60])
    hdr = parse_header(data)
    assert hdr.format == fmt
    assert hdr.size == len(text)
    assert (None if hdr.width is None else (hdr.width, hdr.height)) == geometry


def test_header_binary_percent_is_data():
    # No `% end`: a data word whose low byte is '%' must not be read as a header line.
    data = b"% evt 3.0\n" + np.array([0x2025, 0x8001, 0x000A], "<u2").tobytes()
    assert parse_header(data).size == len(b"% evt 3.0\n")


@pytest.mark.parametrize(
    "text",
    [
        "% evt 3.0\n% geometry 12x\n",
        "% evt 3.0\n% format EVT3;width=640;height=480\n% geometry 1280x720\n",
        "% evt 2.0\n% format EVT3\n",
        "% evt 9.9\n",
        "% evt 3.0\n% width 640\n",
    ],
)
def test_bad_headers_raise(text):
    with pytest.raises(ValueError):
        parse_header(text.encode())


def test_written_header_and_geometry(tmp_path):
    ev = random_stream(1, 50, width=640, height=480)
    write_evt3(tmp_path / "a.raw", ev, extra_header={"serial_number": "42"})
    reader = EventReader(tmp_path / "a.raw")
    assert reader.header.format == "evt3" and reader.header.has_end
    assert (reader.width, reader.height, reader.geometry_source) == (640, 480, "header")
    assert reader.header.get("serial_number") == "42"
    assert reader.header.get("geometry") == "640x480"


# --- round trips ---
@FAST
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 300),
    size=st.sampled_from([(1280, 720), (2048, 2048), (1, 1), (13, 7)]),
    span=st.sampled_from([0, 1, 50, 5_000, 10_000_000, 40_000_000]),
    t0=st.sampled_from([0, 4095, 2**24 - 3, 3 * 2**24 + 17]),
    clustered=st.booleans(),
    triggers=st.integers(0, 5),
)
def test_roundtrip_identity(
    tmp_path_factory, seed, n, size, span, t0, clustered, triggers
):
    ev = random_stream(
        seed,
        n,
        width=size[0],
        height=size[1],
        t0=t0,
        span=span,
        clustered=clustered,
        triggers=triggers,
    )
    back = roundtrip(tmp_path_factory.mktemp("rt"), ev)
    assert_same(ev, back)  # exact, order included


@FAST
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 200),
    block=st.integers(1, 40),
    span=st.sampled_from([3, 300, 60_000_000]),
    triggers=st.integers(0, 6),
    reorder=st.booleans(),
)
def test_blockwise_encoding(tmp_path_factory, seed, n, block, span, triggers, reorder):
    # The writer encodes blocks of events cut at µs changes; small blocks must give
    # the same stream as one block (boundaries inside long µs runs, gaps, triggers).
    ev = random_stream(seed, n, span=span, triggers=triggers)
    whole = encode_evt3_words(ev, reorder=reorder)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_evt3_encode, "BLOCK_EVENTS", block)
        blocked = encode_evt3_words(ev, reorder=reorder)
        assert evt3_word_count(ev, reorder=reorder) == blocked.size
        path = tmp_path_factory.mktemp("blk") / "b.raw"
        write_evt3(path, ev, reorder=reorder)
    np.testing.assert_array_equal(whole, blocked)
    back = read_events(path, strict=True)
    if not reorder:
        assert_same(ev, back)


@FAST
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 300))
def test_roundtrip_reorder_canonical(tmp_path_factory, seed, n):
    ev = random_stream(seed, n, span=20, clustered=False)
    back = roundtrip(tmp_path_factory.mktemp("rt"), ev, reorder=True)
    key = lambda e: np.lexsort((e.p, e.x, e.y, e.t_us))  # noqa: E731
    assert_same(ev.take(key(ev)), back.take(key(back)))


def test_roundtrip_edges(tmp_path):
    # Empty, one event, max coordinates, gaps of several 24-bit wraps, a crowded row.
    empty = mk([], [], [], [], 1280, 720)
    assert_same(empty, roundtrip(tmp_path, empty))
    one = mk([1279], [719], [1], [123_456_789], 1280, 720)
    assert_same(one, roundtrip(tmp_path, one))
    big = mk([2047, 0], [2047, 2047], [0, 1], [5, 5 + 3 * 2**24 + 99], 2048, 2048)
    assert_same(big, roundtrip(tmp_path, big))
    x = np.arange(0, 1280, 1)
    row = mk(x, np.full(x.size, 9), np.ones(x.size), np.full(x.size, 77), 1280, 720)
    back = roundtrip(tmp_path, row)
    assert_same(row, back)
    # A full row needs few words: 1 base + 107 VECT_12 + time + row words.
    assert evt3_word_count(row) < x.size / 10


def test_long_gap_word_layout():
    ev = mk([1, 2], [3, 4], [0, 1], [0, 40_000_000], 1280, 720)
    words = encode_evt3_words(ev)
    th = (words[words >> 12 == 0x8] & 0xFFF).astype(np.int64)
    # TIME_HIGH steps forward by at most 1024 and every wrap is an adjacent 4095 -> 0.
    steps = np.diff(th)
    falls = steps < 0
    assert np.all(steps[~falls] <= 1024)
    assert np.all(th[:-1][falls] == 4095) and np.all(th[1:][falls] == 0)
    assert falls.sum() == 40_000_000 // 2**24


def test_writer_uses_vector_words_and_counts_agree(tmp_path):
    ev = random_stream(5, 5000, span=100)
    words = encode_evt3_words(ev)
    kinds = np.bincount(words >> 12, minlength=16)
    assert kinds[0x3] > 0 and kinds[0x4] > 0 and kinds[0x5] > 0  # VECT_BASE_X, 12, 8
    assert words.size == evt3_word_count(ev)
    write_evt3(tmp_path / "v.raw", ev)
    hdr = EventReader(tmp_path / "v.raw").header.size
    assert (tmp_path / "v.raw").stat().st_size == hdr + 2 * words.size


def test_writer_sorts_unordered_input(tmp_path):
    ev = mk([1, 2, 3], [0, 0, 0], [1, 1, 1], [30, 10, 20], 8, 8)
    assert not ev.is_time_ordered()
    back = roundtrip(tmp_path, ev)
    assert_same(ev.sorted_by_time(), back)


def test_time_order_check():
    """Non-decreasing times (ties allowed) are ordered; one step back is not; an
    empty or one-event stream is."""
    assert mk([1, 2, 3], [0] * 3, [1] * 3, [10, 10, 20], 8, 8).is_time_ordered()
    assert not mk([1, 2, 3], [0] * 3, [1] * 3, [10, 20, 19], 8, 8).is_time_ordered()
    assert mk([], [], [], [], 8, 8).is_time_ordered()
    assert mk([1], [0], [1], [5], 8, 8).is_time_ordered()


@pytest.mark.parametrize(
    "ev, match",
    [
        (mk([0], [0], [0], [0], 2049, 10), "11 bits"),
        (mk([0], [0], [0], [-5], 10, 10), "negative"),
        (
            mk(
                [], [], [], [], 10, 10, trigger_t_us=[1], trigger_p=[1], trigger_id=[16]
            ),
            "0..15",
        ),
    ],
)
def test_writer_rejects(tmp_path, ev, match):
    with pytest.raises(ValueError, match=match):
        write_evt3(tmp_path / "bad.raw", ev)
    assert not list(tmp_path.iterdir())  # atomic: nothing left behind


def test_write_events_dispatch(tmp_path):
    ev = random_stream(3, 100, triggers=3)
    for name in ("a.raw", "a.npz"):
        write_events(tmp_path / name, ev)
        assert_same(ev, read_events(tmp_path / name))
    with pytest.raises(ValueError, match="extension"):
        write_events(tmp_path / "a.txt", ev)
    (tmp_path / "a.dat").write_bytes(b"% evt 3.0\n")
    with pytest.raises(ValueError, match="extension"):
        read_events(tmp_path / "a.dat")


# --- independent decoders ---
@FAST
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 400),
    span=st.sampled_from([30, 100_000, 50_000_000]),
    triggers=st.integers(0, 4),
)
def test_evt3_peer_reads_our_files(tmp_path_factory, seed, n, span, triggers):
    evt3 = pytest.importorskip("evt3")
    ev = random_stream(seed, n, span=span, t0=1000, triggers=triggers)
    path = tmp_path_factory.mktemp("peer") / "p.raw"
    write_evt3(path, ev)
    got, trig = evt3.decode_file_with_triggers(str(path))
    np.testing.assert_array_equal(got.x, ev.x)
    np.testing.assert_array_equal(got.y, ev.y)
    np.testing.assert_array_equal(got.polarity, ev.p)
    np.testing.assert_array_equal(got.t.astype(np.int64), ev.t_us)
    np.testing.assert_array_equal(np.asarray(trig.timestamp, np.int64), ev.trigger_t_us)
    np.testing.assert_array_equal(np.asarray(trig.id), ev.trigger_id)
    np.testing.assert_array_equal(np.asarray(trig.value), ev.trigger_p)


def test_expelliarmus_peer_reads_our_xyp(tmp_path):
    expelliarmus = pytest.importorskip("expelliarmus")
    ev = random_stream(11, 3000, span=200_000, t0=100)
    write_evt3(tmp_path / "e.raw", ev)
    got = expelliarmus.Wizard(encoding="evt3").read(tmp_path / "e.raw")
    np.testing.assert_array_equal(got["x"], ev.x)
    np.testing.assert_array_equal(got["y"], ev.y)
    np.testing.assert_array_equal(got["p"], ev.p)


# --- bad input ---
HEADER = b"% evt 3.0\n% format EVT3;height=720;width=1280\n% end\n"


def raw_file(tmp_path: Path, words, header: bytes = HEADER, tail: bytes = b"") -> Path:
    path = tmp_path / "w.raw"
    path.write_bytes(header + np.asarray(words, "<u2").tobytes() + tail)
    return path


def test_missing_and_headerless_files(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        read_events(tmp_path / "nope.raw")
    (tmp_path / "empty.raw").write_bytes(b"")
    with pytest.raises(ValueError, match="no Prophesee header"):
        read_events(tmp_path / "empty.raw")
    path = raw_file(tmp_path, [0x8001, 0x6002, 0x0005, 0x2007], header=b"")
    with pytest.raises(ValueError, match="no Prophesee header"):
        read_events(path)
    ev = read_events(path, format="evt3")  # forced format: decodes
    assert (len(ev), int(ev.x[0]), int(ev.y[0]), int(ev.t_us[0])) == (1, 7, 5, 4098)
    path = raw_file(tmp_path, [0x8001], header=b"% Date today\n")
    with pytest.raises(ValueError, match="names no event format"):
        read_events(path)
    path = raw_file(tmp_path, [0x8001], header=b"% evt 2.1\n")
    with pytest.raises(ValueError, match="not supported"):
        read_events(path)


def test_header_only_is_empty(tmp_path):
    ev = read_events(raw_file(tmp_path, [], header=b"% evt 3.0"))
    assert len(ev) == 0 and ev.trigger_t_us.size == 0


def test_truncated_odd_byte(tmp_path):
    path = raw_file(tmp_path, [0x8001, 0x6002, 0x0005, 0x2007], tail=b"\x20")
    reader = EventReader(path)
    assert len(reader.read()) == 1 and reader.report.trailing_bytes == 1
    with pytest.raises(ValueError, match="partial 16-bit word"):
        read_events(path, strict=True)


def test_unknown_words_skipped_or_raise(tmp_path):
    path = raw_file(tmp_path, [0x8001, 0x6002, 0x1234, 0x0005, 0x9FFF, 0x2007])
    reader = EventReader(path)
    ev = reader.read()
    assert len(ev) == 1 and reader.report.unknown_words == 2
    with pytest.raises(
        DecodeError, match=rf"reserved word type 0x1 at byte {len(HEADER) + 4}"
    ):
        read_events(path, strict=True)


def test_out_of_geometry(tmp_path):
    words = [0x8001, 0x6002, 0x0005, 0x2007, 0x02D0, 0x2001, 0x0005, 0x2500]
    reader = EventReader(raw_file(tmp_path, words))
    ev = reader.read()  # y=720 and x=1280 are outside 1280x720
    assert len(ev) == 1 and reader.report.out_of_geometry == 2
    with pytest.raises(ValueError, match=r"\(1, 720\) outside the 1280x720"):
        read_events(tmp_path / "w.raw", strict=True)
    assert len(read_events(tmp_path / "w.raw", geometry=(2048, 2048))) == 3


def test_events_before_time_or_row(tmp_path):
    # ADDR_X before any TIME_HIGH, then one before any ADDR_Y, then a vector before
    # any VECT_BASE_X: all three skipped and counted; then a good event.
    words = [0x2001, 0x8000, 0x6001, 0x2002, 0x0003, 0x4FFF, 0x3010, 0x4003]
    reader = EventReader(raw_file(tmp_path, words))
    ev = reader.read()
    assert ev.x.tolist() == [16, 17] and ev.y.tolist() == [3, 3]
    rep = reader.report
    assert (rep.events_before_time, rep.events_without_row) == (1, 1 + 12)
    with pytest.raises(ValueError, match="before the first TIME_HIGH"):
        read_events(tmp_path / "w.raw", strict=True)


def test_time_semantics(tmp_path):
    words = [
        0x8000 | 100,
        0x6000 | 50,
        0x0001,
        0x2001,  # t = 100*4096 + 50
        0x6000 | 40,
        0x2002,  # TIME_LOW steps back 10 µs: held (not a wrap)
        0x8000 | 99,
        0x2003,  # TIME_HIGH falls by 1: a glitch, held
        0x8000 | 101,
        0x2004,  # TIME_HIGH alone resets the low part
        0xA000 | 0x0301,  # trigger channel 3, rising
        0x8000 | 4095,
        0x6005,
        0x2005,
        0x8000,
        0x6006,
        0x2006,  # a 24-bit wrap
        0xE001,
        0xF123,
        0x7004,  # OTHERS + CONTINUED: skipped
    ]
    reader = EventReader(raw_file(tmp_path, words))
    ev = reader.read()
    base = 100 * 4096
    assert ev.t_us.tolist() == [
        base + 50,
        base + 50,
        base + 50,
        101 * 4096,
        4095 * 4096 + 5,
        2**24 + 6,
    ]
    assert ev.x.tolist() == [1, 2, 3, 4, 5, 6]
    assert ev.trigger_t_us.tolist() == [101 * 4096] and ev.trigger_id.tolist() == [3]
    rep = reader.report
    assert (rep.time_clamped, rep.max_step_back_us, rep.time_glitches) == (2, 4146, 1)
    assert (rep.time_wraps, rep.other_words, rep.defects) == (1, 3, 0)


def test_system_type_bit_is_not_part_of_y(tmp_path):
    reader = EventReader(raw_file(tmp_path, [0x8000, 0x6001, 0x0800 | 5, 0x2007]))
    ev = reader.read()
    assert ev.y.tolist() == [5] and reader.report.system_type_rows == 1


def test_vector_words_decode(tmp_path):
    words = [
        0x8000,
        0x6001,
        0x0002,
        0x3800 | 100,
        0x4000 | 0b100000000101,
        0x5000 | 0x81,
    ]
    ev = read_events(raw_file(tmp_path, words), strict=True)
    assert ev.x.tolist() == [100, 102, 111, 112, 119] and set(ev.p.tolist()) == {1}


def test_describe_generated(tmp_path):
    ev = random_stream(2, 500, triggers=4, span=1_000_000)
    write_evt3(tmp_path / "d.raw", ev)
    info = describe_events(tmp_path / "d.raw")
    assert info["events"] == 500 and info["triggers"] == 4
    assert (
        info["on_events"] == int(ev.p.sum()) and info["duration_us"] == ev.duration_us
    )
    assert info["decode"]["events"] == 500 and info["header"]["evt"] == "3.0"
    empty = mk([], [], [], [], 10, 10)
    write_evt3(tmp_path / "e.raw", empty)
    info = describe_events(tmp_path / "e.raw")
    assert info["events"] == 0 and info["rate_ev_per_s"] is None
