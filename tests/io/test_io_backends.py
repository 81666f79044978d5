"""The compiled (numba) kernels against the NumPy reference, input by input.

The other test_io modules run every test with both backends; here the two decode the
same bytes — whole, in chunks (state carried across boundaries), strict (the same
error, or none), through the window index — and encode the same streams, and must
agree exactly: events, triggers, words and every `DecodeReport` counter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._base import _numba
from evhsi_jax._io import (
    DecodeError,
    EventReader,
    _evt3_encode,
    encode_evt3_words,
    evt3_word_count,
    write_evt3,
)

pytestmark = pytest.mark.skipif(not _numba.numba_available(), reason="no numba")

CHECK = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
COLUMNS = ("x", "y", "p", "t_us", "trigger_t_us", "trigger_p", "trigger_id")
HEADER3 = b"% evt 3.0\n% format EVT3;height=64;width=96\n% end\n"
HEADER2 = b"% evt 2.0\n% geometry 96x64\n% end\n"

# EVT 3.0 words weighted towards the types that carry state; EVT 2.0 words with
# times that step, fall a little and wrap.
# Payloads often sit at the edges: the 96x64 geometry (a vector base 84..86 reaches
# column 95/96 in its last bit), a TIME_HIGH fall of exactly half the range, the
# polarity / system-type bit.
_TYPES3 = [0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA, 0xE, 0xF, 0x7, 0x1, 0xB]
_EDGES3 = [0, 1, 63, 64, 84, 85, 86, 95, 96, 0x7FF, 0x800, 0x800 | 63, 0x800 | 85,
           0x800 | 96, 0xFFF, 2047, 2048, 2049, 4095]  # fmt: skip
words3 = st.lists(
    st.tuples(
        st.sampled_from(_TYPES3),
        st.one_of(st.integers(0, 0xFFF), st.sampled_from(_EDGES3)),
    ).map(lambda tp: (tp[0] << 12) | tp[1]),
    max_size=300,
)
_TYPES2 = [0x0, 0x1, 0x8, 0xA, 0xE, 0xF, 0x3]
words2 = st.lists(
    st.tuples(
        st.sampled_from(_TYPES2),
        st.integers(0, 0x3F),
        st.sampled_from([0, 1, 50, 95, 96, 2047]),
        st.sampled_from([0, 7, 63, 64, 2047]),
        st.sampled_from([0, 1, 5, 1 << 27, (1 << 27) + 1, (1 << 28) - 1]),
    ).map(
        lambda v: (
            (v[0] << 28) | (v[4] if v[0] == 0x8 else (v[1] << 22) | (v[2] << 11) | v[3])
        )
    ),
    max_size=200,
)


def columns(ev: EventStream) -> tuple:
    return tuple((getattr(ev, k).dtype.str, getattr(ev, k).tolist()) for k in COLUMNS)


def everything(path: Path, chunk_bytes: int) -> dict:
    """What one backend makes of a file, every way it can be read."""
    out = {}
    reader = EventReader(path)
    ev = reader.read()
    out["read"] = columns(ev), reader.report.as_dict()
    reader = EventReader(path, chunk_bytes=chunk_bytes)
    parts = list(reader)
    whole = EventStream.concatenate(parts) if parts else ev
    out["chunks"] = len(parts), columns(whole), reader.report.as_dict()
    for cb in (chunk_bytes, 1 << 19):
        for how in ("read", "iterate"):
            reader = EventReader(path, strict=True, chunk_bytes=cb)
            try:
                got = reader.read() if how == "read" else list(reader)
            except DecodeError as err:
                out["strict", cb, how] = str(err)
            else:
                got = got if how == "read" else len(got)
                out["strict", cb, how] = columns(got) if how == "read" else got
    reader = EventReader(path, chunk_bytes=chunk_bytes)
    t = ev.t_us.tolist() + ev.trigger_t_us.tolist()
    for t0, t1 in ((min(t, default=0), max(t, default=0) + 1), (0, 2**24 + 5)):
        part = reader.read_window(t0, t1)
        out["window", t0, t1] = columns(part), reader.report.as_dict()
    out["index"] = [
        (c.offset, c.nbytes, c.t_lo, c.t_hi, c.g_lo, c.g_hi, c.n_events, c.n_triggers)
        for c in reader._index
    ]
    return out


def both(path: Path, chunk_bytes: int) -> tuple[dict, dict]:
    with _numba.use_backend("numba"):
        fast = everything(path, chunk_bytes)
    with _numba.use_backend("numpy"):
        ref = everything(path, chunk_bytes)
    return fast, ref


@CHECK
@given(
    words=st.one_of(words3, st.lists(st.integers(0, 0xFFFF), max_size=300)),
    chunk_bytes=st.integers(1, 200),
    tail=st.sampled_from([b"", b"\x20"]),
)
def test_evt3_backends_agree(tmp_path, words, chunk_bytes, tail):
    path = tmp_path / "w3.raw"
    path.write_bytes(HEADER3 + np.asarray(words, "<u2").tobytes() + tail)
    fast, ref = both(path, chunk_bytes)
    assert fast == ref


@CHECK
@given(words=words2, chunk_bytes=st.integers(1, 100))
def test_evt2_backends_agree(tmp_path, words, chunk_bytes):
    path = tmp_path / "w2.raw"
    path.write_bytes(HEADER2 + np.asarray(words, "<u4").tobytes())
    fast, ref = both(path, chunk_bytes)
    assert fast == ref


def test_strict_error_order_follows_chunks(tmp_path):
    # An event outside 96x64 (word 3), then a reserved word (word 4). Within one chunk
    # the reference reports the scan defect first (geometry is checked after the
    # scan); when the outside event's chunk comes first, that one. Both backends.
    words = [0x8001, 0x6002, 0x0005, 0x2000 | 100, 0x1234]
    path = tmp_path / "d.raw"
    path.write_bytes(HEADER3 + np.asarray(words, "<u2").tobytes())
    at = len(HEADER3)
    for name in ("numba", "numpy"):
        with _numba.use_backend(name):
            # 7: word 3 straddles the cut at byte 7, so it is completed in chunk 1.
            for cb, what in (
                (10, "reserved word type 0x1"),
                (8, r"\(100, 5\) outside"),
                (7, "reserved word type 0x1"),
            ):
                with pytest.raises(DecodeError, match=what):
                    EventReader(path, strict=True, chunk_bytes=cb).read()
            with pytest.raises(DecodeError, match=f"at byte {at + 8} "):
                EventReader(path, strict=True).read()


def random_stream(seed: int, n: int, span: int, t0: int, triggers: int):
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(t0, t0 + span + 1, n))
    x = rng.integers(0, 1280, n)
    y = rng.integers(0, 720, n)
    p = rng.integers(0, 2, n)
    if n > 1:  # runs of one µs, row and polarity with stepping columns
        run = rng.random(n) < 0.7
        run[0] = False
        start = np.maximum.accumulate(np.where(run, 0, np.arange(n)))
        t, y, p = t[start], y[start], p[start]
        step = np.cumsum(rng.integers(1, 14, n))
        x = np.minimum(x[start] + step - step[start], 1279)
    gt = np.sort(rng.integers(t0, t0 + span + 1, triggers))
    return EventStream(
        x, y, p, t, 1280, 720, trigger_t_us=gt,
        trigger_p=rng.integers(0, 2, triggers), trigger_id=rng.integers(0, 16, triggers),
    )  # fmt: skip


@CHECK
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 400),
    span=st.sampled_from([0, 3, 300, 70_000, 50_000_000]),
    t0=st.sampled_from([0, 4095, 2**24 - 2, 5 * 2**24 + 3]),
    triggers=st.integers(0, 6),
    reorder=st.booleans(),
    block=st.sampled_from([1, 7, 1 << 20]),
)
def test_encoders_agree(tmp_path, seed, n, span, t0, triggers, reorder, block):
    ev = random_stream(seed, n, span, t0, triggers)
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_evt3_encode, "BLOCK_EVENTS", block)
        for name in ("numba", "numpy"):
            with _numba.use_backend(name):
                path = tmp_path / f"{name}.raw"
                write_evt3(path, ev, reorder=reorder)
                words = encode_evt3_words(ev, reorder=reorder)
                count = evt3_word_count(ev, reorder=reorder)
                out[name] = words.tolist(), count, path.read_bytes()
    assert out["numba"] == out["numpy"]
    assert out["numba"][1] == len(out["numba"][0])


def test_unsorted_stream_encodes_alike():
    ev = random_stream(3, 500, 1000, 0, 3)
    shuffled = ev.take(np.random.default_rng(0).permutation(len(ev)))
    words = {}
    for name in ("numba", "numpy"):
        with _numba.use_backend(name):
            words[name] = encode_evt3_words(shuffled).tolist()
    assert words["numba"] == words["numpy"]


def test_backend_switch(monkeypatch):
    monkeypatch.setenv(_numba.ENV_DISABLE, "1")
    assert not _numba.use_numba()
    with _numba.use_backend("numba"):
        assert _numba.use_numba()
    monkeypatch.setenv(_numba.ENV_DISABLE, "0")
    assert _numba.use_numba()
    with _numba.use_backend("numpy"):
        assert not _numba.use_numba()
    with pytest.raises(ValueError, match="backend"):
        with _numba.use_backend("cython"):
            pass


def test_njit_without_a_cache_folder(monkeypatch):
    numba = pytest.importorskip("numba")
    real = numba.njit

    def no_cache(*args, **kw):  # numba raises like this when no folder is writable
        if kw.get("cache"):
            raise RuntimeError("cannot cache function: no locator available")
        return real(*args, **kw)

    monkeypatch.setattr(numba, "njit", no_cache)
    f = _numba.njit(lambda a: a + 1)
    assert f(41) == 42


def test_decoded_streams_are_valid(tmp_path):
    # The reader skips `EventStream` validation (the decoder guarantees it): check
    # that a validating constructor accepts what it returns.
    path = tmp_path / "v.raw"
    write_evt3(path, random_stream(5, 3000, 10_000, 7, 4))
    for name in ("numba", "numpy"):
        with _numba.use_backend(name):
            ev = EventReader(path).read()
        again = EventStream(*(getattr(ev, k) for k in COLUMNS[:4]), ev.width,
                            ev.height, *(getattr(ev, k) for k in COLUMNS[4:]))  # fmt: skip
        assert columns(again) == columns(ev) and len(ev) == 3000


def _report(path: Path, **kw) -> tuple:
    reader = EventReader(path, **kw)
    return columns(reader.read()), reader.report.as_dict()


@pytest.mark.parametrize(
    "words, header, expect",
    [
        # TIME_HIGH falls of exactly half the range (a glitch) and one more (a wrap).
        ([0x8800, 0x8000, 0x0001, 0x2001], HEADER3, {"time_glitches": 1}),
        ([0x8801, 0x8000, 0x0001, 0x2001], HEADER3, {"time_wraps": 1}),
        # Vectors at the right edge of 96 columns: 84..95 fit, 85..96 do not.
        ([0x8000, 0x0001, 0x3000 | 84, 0x4FFF], HEADER3, {"events": 12}),
        ([0x8000, 0x0001, 0x3000 | 85, 0x4FFF], HEADER3, {"out_of_geometry": 1}),
        ([0x8000, 0x0001, 0x3000 | 76, 0x4FFF, 0x50FF], HEADER3, {"events": 20}),
        ([0x8000, 0x0001, 0x3000 | 77, 0x4FFF, 0x50FF], HEADER3, {"events": 19}),
        (
            [0x8000, 0x0040, 0x2001, 0x0800 | 63, 0x2001],
            HEADER3,
            {"system_type_rows": 1},
        ),
        # EVT 2.0: falls of exactly 2**27 (a glitch) and one more (a wrap).
        ([0x88000000, 0x80000000, 0x10000801], HEADER2, {"time_glitches": 1}),
        ([0x88000001, 0x80000000, 0x10000801], HEADER2, {"time_wraps": 1}),
    ],
)
def test_edges_decode_alike(tmp_path, words, header, expect):
    dtype = "<u2" if header is HEADER3 else "<u4"
    path = tmp_path / "e.raw"
    path.write_bytes(header + np.asarray(words, dtype).tobytes())
    got = {}
    for name in ("numba", "numpy"):
        with _numba.use_backend(name):
            got[name] = _report(path), _report(path, chunk_bytes=1)
    assert got["numba"] == got["numpy"]
    report = got["numpy"][0][1]
    assert {k: report[k] for k in expect} == expect


@pytest.mark.parametrize("span", [1, 50, 10**9])
def test_stable_integer_argsort_matches_numpy(span):
    # The simulator's O(n) counting sort of event times must give NumPy's stable
    # permutation (equal keys keep their order); a wide range falls back to NumPy.
    from evhsi_jax._base import stable_argsort_int

    keys = np.random.default_rng(span).integers(-5, span, 5000)
    ref = np.argsort(keys, kind="stable")
    for name in ("numba", "numpy"):
        if name == "numba" and not _numba.numba_available():
            continue
        with _numba.use_backend(name):
            np.testing.assert_array_equal(stable_argsort_int(keys), ref)
    assert stable_argsort_int(np.zeros(0)).shape == (0,)
    with pytest.raises(ValueError, match="integer"):
        stable_argsort_int(np.array([0.5, 1.5]))
