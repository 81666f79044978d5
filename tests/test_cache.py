"""The start-up cache of traced kernels (`evhsi_jax._base._cache.call_exported`):
same results as the kernel itself, no tracing in a process that finds the stored
program, a key that separates what the trace depends on, and a fall-back for every
failure."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._base import _cache

TRACES = []


def kernel(x, table, scale, mode):
    """A small kernel with an array pytree, a static Python leaf and a closure-free
    body; counts its traces."""
    TRACES.append(mode)
    y = x @ table["a"] + table["b"]
    return jnp.tanh(y) * scale if mode == "tanh" else y * scale


@pytest.fixture
def cache_on(tmp_path, monkeypatch):
    """The cache switched on in a private folder, with an empty in-process memo (as a
    new process would have)."""
    monkeypatch.setattr(_cache, "_ENABLED", [tmp_path])
    monkeypatch.setattr(_cache, "_EXPORTED", {})
    monkeypatch.setattr(_cache, "_COMPILED", {})
    monkeypatch.setattr(_cache, "_PREPARING", {})
    TRACES.clear()
    return tmp_path / "exported"


def _args(n=4, mode="tanh"):
    rng = np.random.default_rng(0)
    x = rng.standard_normal((n, 3)).astype(np.float32)
    table = {"a": jnp.asarray(rng.standard_normal((3, 2)), jnp.float32),
             "b": np.float32(0.5)}  # fmt: skip
    return (x, table, np.float32(2.0), mode)


def test_stored_program_equals_kernel_and_skips_tracing(cache_on):
    args = _args()
    want = np.asarray(eqx.filter_jit(kernel)(*args))
    TRACES.clear()
    got = np.asarray(_cache.call_exported("k", kernel, args))
    np.testing.assert_array_equal(got, want)
    assert len(TRACES) == 1 and len(list(cache_on.glob("k-*.bin"))) == 1
    # A new process: empty memo, the file is there -> no trace at all.
    _cache._EXPORTED.clear()
    TRACES.clear()
    again = np.asarray(_cache.call_exported("k", kernel, _args()))
    np.testing.assert_array_equal(again, want)
    assert TRACES == []
    # New values of the same shapes reuse the program (values are inputs, not keys).
    other = (args[0] + 1.0, *args[1:])
    np.testing.assert_array_equal(
        np.asarray(_cache.call_exported("k", kernel, other)),
        np.asarray(eqx.filter_jit(kernel)(*other)),
    )
    assert len(list(cache_on.glob("k-*.bin"))) == 1


@pytest.mark.parametrize("change", ["shape", "static_leaf", "static_arg", "dtype"])
def test_key_separates_what_the_trace_depends_on(cache_on, change):
    _cache.call_exported("k", kernel, _args())
    if change == "shape":
        args, static = _args(n=5), ()
    elif change == "static_leaf":  # a Python leaf of the arguments
        args, static = _args(mode="linear"), ()
    elif change == "static_arg":  # a value the function closes over
        args, static = _args(), ("other",)
    else:
        args = jax.tree.map(
            lambda a: a.astype(jnp.float16) if eqx.is_array(a) else a, _args()
        )
        static = ()
    got = _cache.call_exported("k", kernel, args, static=static)
    np.testing.assert_array_equal(
        np.asarray(got), np.asarray(eqx.filter_jit(kernel)(*args))
    )
    assert len(list(cache_on.glob("k-*.bin"))) == 2


def test_a_program_prepared_in_the_background_is_the_one_called(cache_on):
    """`prepare_exported` compiles in a background thread what the same call of
    `call_exported` then runs: the same results, one trace, and no second
    compilation; the float64 setting of the caller holds in the thread. A failure
    there is only a missed start: `call_exported` falls back as usual."""
    with jax.enable_x64(True):
        args = jax.tree.map(
            lambda a: jnp.asarray(a, jnp.float64) if eqx.is_array(a) else a, _args()
        )
        want = np.asarray(eqx.filter_jit(kernel)(*args))
        TRACES.clear()
        _cache.prepare_exported("p", kernel, args)
        _cache.prepare_exported("p", kernel, args)  # already under way: nothing more
        assert len(_cache._PREPARING) == 1
        got = _cache.call_exported("p", kernel, args)
        assert got.dtype == jnp.float64
        np.testing.assert_array_equal(np.asarray(got), want)
        assert TRACES == ["tanh"] and len(_cache._COMPILED) == 1
        assert not _cache._PREPARING
        # other values, same shapes: the compiled program, no new trace
        other = (args[0] + 1.0, *args[1:])
        np.testing.assert_array_equal(
            np.asarray(_cache.call_exported("p", kernel, other)),
            np.asarray(eqx.filter_jit(kernel)(*other)),
        )
        assert TRACES == ["tanh"]

    def broken(*a):
        raise RuntimeError("no")

    _cache.prepare_exported("b", broken, _args())
    with pytest.raises(RuntimeError, match="no"):  # the kernel's own error, not lost
        _cache.call_exported("b", broken, _args())


def test_damaged_file_is_replaced(cache_on):
    want = np.asarray(_cache.call_exported("k", kernel, _args()))
    (path,) = cache_on.glob("k-*.bin")
    path.write_bytes(b"not a program")
    _cache._EXPORTED.clear()
    np.testing.assert_array_equal(
        np.asarray(_cache.call_exported("k", kernel, _args())), want
    )
    assert path.read_bytes() != b"not a program"


def test_off_and_failures_fall_back(cache_on, monkeypatch):
    def untraceable(x, table, scale, mode):  # data-dependent Python control flow
        return x * 2 if float(np.asarray(x).sum()) > -1e9 else x

    args = _args()
    np.testing.assert_array_equal(
        np.asarray(_cache.call_exported("u", untraceable, args)), args[0] * 2
    )
    assert list(cache_on.glob("u-*.bin")) == []
    monkeypatch.setattr(_cache, "_ENABLED", [])  # cache off: plain call, no file
    _cache.call_exported("off", kernel, args)
    assert list(cache_on.glob("off-*.bin")) == []


def test_reconstruction_through_stored_programs(cache_on, monkeypatch):
    """`ev.reconstruct` (its JAX backend) with the cache on: the cube of a second
    process (empty memo, stored programs) equals that of the kernels run directly,
    bit for bit."""
    scene = ev.load_scene("colorchecker", (8, 12))
    rig = ev.Rig()
    events = ev.simulate(scene, rig, key=jax.random.key(3))
    first = ev.reconstruct(events, rig, backend="jax")
    assert list(cache_on.glob("reconstruct_chunk-*.bin"))
    _cache._EXPORTED.clear()
    second = ev.reconstruct(events, rig, backend="jax")
    monkeypatch.setattr(_cache, "_ENABLED", [])
    direct = ev.reconstruct(events, rig, backend="jax")
    np.testing.assert_array_equal(first, direct)
    np.testing.assert_array_equal(second, direct)


def _kernel(folder, module: str, body: str):
    """The cached numba kernel `def <body>` of a module `module` written to `folder`
    (through `evhsi_jax._base.njit`), not compiled yet; skips without numba."""
    import importlib
    import sys

    pytest.importorskip("numba")
    name = body.split("(")[0]
    (folder / f"{module}.py").write_text(
        f"from evhsi_jax._base import njit\n\n\n@njit\ndef {body}\n"
    )
    sys.path.insert(0, str(folder))
    try:
        return getattr(importlib.import_module(module), name)
    finally:
        sys.path.remove(str(folder))
        sys.modules.pop(module, None)


def test_a_kernel_compiling_elsewhere_is_waited_for(tmp_path):
    """A numba kernel's compilation holds a lock file beside its cache entry
    (`_numba._with_compile_lock`): a process that needs the kernel while another
    holds it waits, then compiles or loads it — processes started together on a
    fresh install compile each kernel once."""
    import fcntl
    import os
    import subprocess
    import sys
    import time

    add = _kernel(tmp_path, "kmod", "add(a, b):\n    return a + b")
    lock = add._cache._cache_file._index_path + ".lock"
    os.makedirs(os.path.dirname(lock), exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)  # as a process compiling it would
    code = (
        "import sys, time; sys.path.insert(0, sys.argv[1]); import kmod\n"
        "print('ready', flush=True); t = time.monotonic()\n"
        "assert kmod.add(1, 2) == 3; print(time.monotonic() - t, flush=True)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)],
                            stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(1.5)
        assert proc.poll() is None  # waiting for the lock
    finally:
        os.close(fd)  # released: it goes on
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0
    assert float(out.strip()) >= 1.4


def test_a_file_system_without_locks_compiles_at_once(tmp_path, monkeypatch):
    """Where the cache's file system refuses locks (`flock` fails otherwise than by
    being held), a kernel compiles without one, at once — not after waiting."""
    import errno
    import fcntl

    from evhsi_jax._base import _numba

    mul = _kernel(tmp_path, "kmod2", "mul(a, b):\n    return a * b")
    calls = []

    def refuse(fd, op):
        calls.append(op)
        raise OSError(errno.ENOLCK, "no locks available")

    monkeypatch.setattr(fcntl, "flock", refuse)
    monkeypatch.setattr(_numba, "COMPILE_LOCK_WAIT_S", 2.0)
    assert mul(3, 4) == 12
    assert len(calls) == 1  # tried once, then compiled
