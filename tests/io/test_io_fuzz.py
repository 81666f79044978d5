"""Fuzzing the readers with random and mutated word streams.

Properties, for any input: decoding terminates (the decoders loop only over chunks of a
finite file and the header scan is capped, so there is nothing to time out), raises
nothing but `ValueError`, and what it returns keeps the `EventStream` invariants
(coordinates inside the geometry, polarity 0/1, non-decreasing timestamps). Lenient
decoding never raises once the header is valid, and does not depend on chunk size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from evhsi_jax import EventStream
from evhsi_jax._io import DecodeReport, EventReader, write_evt3
from evhsi_jax._io._evt3_decode import Evt3State, carry_evt3_state, scan_evt3_words

FUZZ = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
HEADER3 = b"% evt 3.0\n% format EVT3;height=64;width=96\n% end\n"
HEADER2 = b"% evt 2.0\n% geometry 96x64\n% end\n"


# Every test here runs with the compiled kernels and with the NumPy reference.
pytestmark = pytest.mark.usefixtures("io_backend")


# Word types weighted towards the ones that carry state, so streams go deep.
_TYPES3 = [0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA, 0xE, 0xF, 0x7, 0x1, 0xB]
words3 = st.lists(
    st.tuples(st.sampled_from(_TYPES3), st.integers(0, 0xFFF)).map(
        lambda tp: (tp[0] << 12) | tp[1]
    ),
    max_size=400,
)
raw_words = st.lists(st.integers(0, 0xFFFF), max_size=400)


def check_invariants(ev: EventStream, width: int = 96, height: int = 64) -> None:
    assert (ev.width, ev.height) == (width, height)
    if len(ev):
        assert int(ev.x.max()) < width and int(ev.y.max()) < height
        assert int(ev.p.max()) <= 1
        assert np.all(np.diff(ev.t_us) >= 0)
        assert int(ev.t_us.min()) >= 0
    assert np.all(np.diff(ev.trigger_t_us) >= 0)


def decode(path: Path, **kw) -> tuple[EventStream, dict]:
    reader = EventReader(path, **kw)
    ev = reader.read()
    return ev, reader.report.as_dict()


def decode_chunked(
    path: Path, chunk_bytes: int, workers: int = 1
) -> tuple[EventStream, dict]:
    reader = EventReader(path, chunk_bytes=chunk_bytes, workers=workers)
    parts = list(reader)
    ev = EventStream.concatenate(parts) if parts else EventReader(path).read()
    return ev, reader.report.as_dict()


def same(a: EventStream, b: EventStream) -> bool:
    cols = ("x", "y", "p", "t_us", "trigger_t_us", "trigger_p", "trigger_id")
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in cols)


@FUZZ
@given(words=st.one_of(words3, raw_words), chunk_bytes=st.integers(1, 300))
def test_evt3_random_words(tmp_path, words, chunk_bytes):
    path = tmp_path / "f.raw"
    path.write_bytes(HEADER3 + np.asarray(words, "<u2").tobytes())
    ev, report = decode(path)
    check_invariants(ev)
    assert report["words"] == len(words) and report["events"] == len(ev)
    ev2, report2 = decode_chunked(path, chunk_bytes)
    assert same(ev, ev2) and report == report2
    ev3, report3 = decode_chunked(path, chunk_bytes, workers=2)  # predicted states
    assert same(ev, ev3) and report == report3
    defects = sum(report[k] for k in DecodeReport.DEFECTS)
    try:
        strict = EventReader(path, strict=True).read()
    except ValueError:
        assert defects > 0  # strict mode raises exactly when lenient mode skips
    else:
        assert defects == 0 and same(ev, strict)


@FUZZ
@given(
    seed=st.integers(0, 2**32 - 1),
    ops=st.lists(
        st.tuples(
            st.sampled_from(["flip", "cut", "insert", "delete", "dup"]),
            st.floats(0, 1),
            st.integers(0, 255),
        ),
        min_size=1,
        max_size=6,
    ),
)
def test_evt3_mutated_files(tmp_path, seed, ops):
    rng = np.random.default_rng(seed)
    n = 200
    t = np.sort(rng.integers(0, 3 * 2**24, n))
    ev = EventStream(
        rng.integers(0, 96, n),
        rng.integers(0, 64, n),
        rng.integers(0, 2, n),
        t,
        96,
        64,
        trigger_t_us=np.sort(rng.integers(0, 3 * 2**24, 3)),
        trigger_p=np.ones(3, np.int64),
        trigger_id=np.zeros(3, np.int64),
    )
    path = tmp_path / "m.raw"
    write_evt3(path, ev)
    data = bytearray(path.read_bytes())
    body = EventReader(path).header.size  # mutate the words, not the header
    for op, where, value in ops:
        at = body + int(where * max(len(data) - body - 1, 0))
        if op == "flip" and at < len(data):
            data[at] ^= value | 1
        elif op == "cut":
            del data[at:]
        elif op == "insert":
            data[at:at] = bytes([value]) * (1 + value % 5)
        elif op == "delete":
            del data[at : at + 1 + value % 7]
        elif op == "dup":
            data[at:at] = data[at : at + 2 + value % 9]
    path.write_bytes(bytes(data))
    got, report = decode(path)
    check_invariants(got)
    assert report["events"] == len(got)
    got2, report2 = decode_chunked(path, 16 + seed % 97, workers=1 + seed % 2)
    assert same(got, got2) and report == report2


@FUZZ
@given(data=st.binary(max_size=600), header=st.sampled_from([b"", HEADER3, b"%"]))
def test_arbitrary_bytes(tmp_path, data, header):
    path = tmp_path / "b.raw"
    path.write_bytes(header + data)
    try:
        ev = EventReader(path).read()
    except ValueError:
        return  # no header, or a header that does not parse: a clear error
    assert ev.width > 0 and ev.height > 0
    assert len(ev) == 0 or np.all(np.diff(ev.t_us) >= 0)


@FUZZ
@given(
    words=st.lists(st.integers(0, 2**32 - 1), max_size=200), chunk=st.integers(1, 99)
)
def test_evt2_random_words(tmp_path, words, chunk):
    path = tmp_path / "e.raw"
    path.write_bytes(HEADER2 + np.asarray(words, "<u4").tobytes())
    ev, report = decode(path)
    check_invariants(ev)
    assert report["words"] == len(words)
    ev2, report2 = decode_chunked(path, chunk, workers=2)
    assert same(ev, ev2) and report == report2


@FUZZ
@given(words=st.one_of(words3, raw_words), cut=st.integers(0, 400))
def test_evt3_carry_predicts_the_scan(words, cut):
    """The cheap state prediction that lets chunks be scanned in parallel agrees with
    the state a full scan leaves, from any start state."""
    w = np.asarray(words, np.uint16)
    start = Evt3State()
    scan_evt3_words(w[:cut], start, report=DecodeReport())  # some realistic state
    before = start.copy()
    scan_evt3_words(w[cut:], start, report=DecodeReport())
    predicted = carry_evt3_state(w[cut:], before)
    for name in ("y", "base_x", "vpol", "th", "time"):
        assert getattr(predicted, name) == getattr(start, name), name
