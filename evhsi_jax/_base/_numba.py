"""Choosing between the compiled (numba) kernels and the vectorised NumPy reference.

Host-side hot loops — EVT 3.0 and EVT 2.0 decoding and EVT 3.0 encoding (`_io`), the
counting sort of integer keys (`_sorting`: the simulator's events by time, the
reconstruction's by pixel) and the reconstruction's screening and slot filling
(`_reconstruct/_group_jit`) — exist twice: as vectorised NumPy (the reference) and as
numba kernels that make one sequential pass. The event-file kernels (`_decode_jit`,
`_encode_jit`, references `_evt3_decode`, `_evt2`, `_evt3_encode`) carry the same state
word by word and give bit-identical events, words and `DecodeReport` counters, and
raise the same `DecodeError` in strict mode; the tests run every case through both
paths. The kernels are the default when numba imports;
`EVHSI_NO_NUMBA=1` (or `use_backend("numpy")`) selects the NumPy path.

numba is imported lazily, on the first use of a kernel, so `import evhsi_jax` does not
pay for it, and an import failure (numba missing, or built for another NumPy) only means
the NumPy path is used. Kernels are compiled on first use and cached on disk
(`cache=True`: next to this module, or numba's user-wide cache folder when the package
is not writable; without any writable location they are compiled once per process).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator

import numpy as np

__all__ = ["numba_available", "use_numba", "use_backend", "njit", "readonly"]

ENV_DISABLE = "EVHSI_NO_NUMBA"
_numba_ok: bool | None = None
_forced: str | None = None  # "numba" / "numpy" inside `use_backend`


def numba_available() -> bool:
    """True when numba imports (checked once per process)."""
    global _numba_ok
    if _numba_ok is None:
        try:
            import numba  # noqa: F401
        except Exception:  # missing, or incompatible with this NumPy
            _numba_ok = False
        else:
            _numba_ok = True
    return _numba_ok


def use_numba() -> bool:
    """Whether the host-side kernels (decoding, encoding, sorting, grouping) use
    their compiled versions now."""
    if _forced is not None:
        return _forced == "numba"
    flag = os.environ.get(ENV_DISABLE, "").strip().lower()
    if flag not in ("", "0", "false", "no"):
        return False
    return numba_available()


@contextlib.contextmanager
def use_backend(name: str) -> Iterator[None]:
    """Run the block with `"numba"` or `"numpy"` kernels (tests and benchmarks).

    **Arguments:**

    - `name`: `"numba"` (raises `RuntimeError` if numba is unavailable) or `"numpy"`.
    """
    global _forced
    if name not in ("numba", "numpy"):
        raise ValueError(f"backend must be 'numba' or 'numpy', got {name!r}")
    if name == "numba" and not numba_available():
        raise RuntimeError("numba is not available")
    before, _forced = _forced, name
    try:
        yield
    finally:
        _forced = before


def njit(
    fn: Callable | None = None,
    *,
    inline: bool = False,
    fastmath=False,
    slp: bool = False,
    error_model: str = "python",
) -> Callable:
    """`numba.njit(cache=True, nogil=True)`, without the cache when no folder for it is
    writable (numba raises then instead of falling back). `inline=True`: inlined into
    its callers by numba (`inline="always"`; such helpers are not cached themselves).
    `fastmath`: numba's LLVM flags (e.g. `{"reassoc", "contract"}` lets sums be
    vectorised in a different order). `slp=True`: compiled with LLVM's SLP
    vectoriser, which numba switches off process-wide by default (numba PR #8852,
    after miscompilations reported on older LLVM); see :func:`_with_slp`.
    `error_model="numpy"`: a float division by zero gives inf or NaN as in NumPy
    instead of raising — numba's default (`"python"`) tests every divisor, and that
    branch keeps LLVM from vectorising a loop with a division in it."""
    import numba

    if fn is None:
        return lambda f: njit(
            f, inline=inline, fastmath=fastmath, slp=slp, error_model=error_model
        )
    opts = {"fastmath": fastmath, "error_model": error_model}
    if inline:
        return numba.njit(inline="always", **opts)(fn)
    try:
        disp = _with_compile_lock(numba.njit(cache=True, nogil=True, **opts)(fn))
    except RuntimeError:
        disp = numba.njit(nogil=True, **opts)(fn)
    return _with_slp(disp) if slp else disp


#: Longest wait (s) for another process's compilation of a kernel; then this process
#: compiles it itself.
COMPILE_LOCK_WAIT_S = 900.0


def _with_compile_lock(disp):
    """`disp` whose compilations hold a lock file beside its cache entry, so that
    processes started together on a fresh install (the test suite's workers and the
    `evhsi` processes they start; a user's parallel jobs) compile a kernel once: the
    others wait, then load it from numba's cache (numba writes its cache files whole,
    by renaming). The fused reconstruction kernel alone takes ~100 s to compile on
    a 2-core machine (2026-12-07).

    The lock is taken inside numba's compiler lock (one compilation per process at a
    time, so a process's threads never wait for each other's lock file) and a
    kernel's compilation only takes the locks of the kernels it calls: no cycle. No
    lock where `fcntl` is missing (not POSIX), the cache has no folder or its file
    system has no locks; after `COMPILE_LOCK_WAIT_S` of waiting the process
    compiles without it."""
    try:
        import fcntl

        lock_path = disp._cache._cache_file._index_path + ".lock"
    except Exception:  # numba's internals moved, or no POSIX locks: no lock
        return disp
    import time

    from numba.core import sigutils
    from numba.core.compiler_lock import global_compiler_lock

    compile_plain = disp.compile

    def compile(sig):
        with global_compiler_lock:
            try:  # already compiled in this process: no lock to wait for
                if tuple(sigutils.normalize_signature(sig)[0]) in disp.overloads:
                    return compile_plain(sig)
            except Exception:
                pass
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError:  # a read-only cache folder: numba falls back on its own
                return compile_plain(sig)
            try:
                deadline = time.monotonic() + COMPILE_LOCK_WAIT_S
                while True:
                    try:
                        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        break
                    except BlockingIOError:  # held by another process
                        if time.monotonic() > deadline:
                            break
                        time.sleep(0.05)
                    except OSError:  # no locks on this file system: none
                        break
                return compile_plain(sig)
            finally:
                os.close(fd)  # (releases the lock)

    disp.compile = compile
    return disp


def _with_slp(disp):
    """`disp` whose compilations run with numba's `SLP_VECTORIZE` switched on.

    numba reads the flag each time it builds LLVM's pass pipeline, so it is set only
    while this dispatcher compiles (and the functions it calls compile with it),
    under numba's compiler lock, which every compilation in the process takes: no
    other function is compiled with it. What SLP packs is independent scalar
    operations into vector ones, without reordering floating-point arithmetic, so
    the results are those of the scalar code. The object code in numba's cache is
    the one compiled this way (the cache is keyed by the source file, which carries
    this decorator)."""
    from numba.core import config
    from numba.core.compiler_lock import global_compiler_lock

    compile_plain = disp.compile

    def compile(sig):
        with global_compiler_lock:
            before = config.SLP_VECTORIZE
            config.SLP_VECTORIZE = 1
            try:
                return compile_plain(sig)
            finally:
                config.SLP_VECTORIZE = before

    disp.compile = compile
    return disp


def readonly(a: np.ndarray, dtype) -> np.ndarray:
    """`a` as a contiguous read-only array of `dtype`: the kernels see one array type
    whatever the caller holds, so each compiles (and is cached) once."""
    a = np.ascontiguousarray(a, dtype=dtype).view()
    a.flags.writeable = False
    return a
