"""A persistent compilation cache, so a command's second run starts in seconds.

Most of a short command's time is XLA compiling the same kernels again. JAX can keep
compiled executables on disk (its persistent compilation cache, keyed by the program,
the shapes, the JAX/XLA versions and flags, so a stale entry is never used). The `evhsi`
command turns it on; a Python user calls :func:`enable_compilation_cache` (importing
the library changes no global JAX setting).

Where: `$EVHSI_CACHE_DIR` if set (`off` turns the cache off), else
`$XDG_CACHE_HOME/evhsi_jax/jax` (default `~/.cache/evhsi_jax/jax`). The folder is safe
to delete at any time; JAX fills it again as needed.

JAX's cache skips XLA's compilation only: tracing a kernel in Python and lowering it
still happen in every process (~0.4 s for each of the reconstruction's chunk shapes).
:func:`call_exported` therefore also keeps the *traced* program of a hot kernel, as a
serialized `jax.export` module in the folder's `exported/` subfolder, keyed by
everything the trace depends on (the argument structure, shapes, dtypes and
shardings, the static arguments, the devices, the JAX version and the package's own
source), so a second process calls it without tracing. Same folder, same rules: on
only while the compilation cache is on, safe to delete, and never a reason to fail
(any problem falls back to calling the kernel directly).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.tree_util as jtu

from ._storage import atomic_write

__all__ = ["enable_compilation_cache", "cache_dir", "call_exported", "prepare_exported"]

_ENABLED: list[Path] = []


def cache_dir() -> Path | None:
    """The cache folder the settings name (None when turned off)."""
    env = os.environ.get("EVHSI_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "none") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "evhsi_jax" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in `path` (default: `cache_dir()`).

    Every compilation is cached (not only those over JAX's default 1 s threshold:
    ours are many small kernels). Returns the folder, or None when the cache is off or
    the folder cannot be created (then nothing changes: the cache is an optimisation,
    never a reason to fail).
    """
    folder = Path(path) if path is not None else cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _ENABLED[:] = [folder]
    return folder


# --- traced programs kept on disk (jax.export) ----------------------------------------
_EXPORTED: dict[str, object] = {}  # key -> jax.export.Exported, this process
_SOURCE_DIGEST: list[str] = []


def _source_digest() -> str:
    """A digest of the package's Python source: an exported program is a trace of
    this code, so any change of it must miss the cache."""
    if not _SOURCE_DIGEST:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for f in sorted(root.rglob("*.py")):
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
        _SOURCE_DIGEST.append(h.hexdigest())
    return _SOURCE_DIGEST[0]


def _serialization_available() -> bool:
    try:
        import flatbuffers  # noqa: F401  (jax.export's serializer needs it)
    except ImportError:
        return False
    return True


def call_exported(name: str, fn, args: tuple, *, static: tuple = (), mesh=None):
    """`fn(*args)`, through a traced copy of `fn` kept on disk when the compilation
    cache is on (see the module docstring); plain `fn(*args)` otherwise.

    **Arguments:**

    - `name`: the kernel's name (part of the key and the file name).
    - `fn`: a function JAX can trace (jitted or not); its result must be arrays.
    - `args`: its arguments, pytrees; array leaves (JAX or NumPy) become the
      program's inputs, every other leaf is part of the key (its `repr`), as with
      `equinox.filter_jit`.
    - `static`: whatever else `fn`'s program depends on that is not in `args` (the
      values it closes over): part of the key.
    - `mesh`: the device mesh `fn` runs on (a `shard_map` inside): leaves not already
      spread over several devices are replicated on it. `None`: one device.

    **Returns:** what `fn(*args)` returns (bit for bit: the same program).
    """
    folder = _exported_folder()
    if folder is None:
        return fn(*args)
    key, leaves, specs, treedef, kept = _signature(name, fn, args, static, mesh)
    pending = _PREPARING.pop(key, None)
    if pending is not None:  # compiled in the background (prepare_exported)
        try:
            compiled = pending.result()
        except Exception:  # never a reason to fail: compiled here instead
            compiled = None
        if compiled is not None:
            while len(_COMPILED) >= _MAX_COMPILED:  # the oldest out (dicts keep order)
                _COMPILED.pop(next(iter(_COMPILED)))
            _COMPILED[key] = compiled
    if key in _COMPILED:
        return _COMPILED[key](*leaves)
    exp = _exported(folder, key, fn, treedef, kept, specs)
    return fn(*args) if exp is None else exp.call(*leaves)


def prepare_exported(name: str, fn, args: tuple, *, static: tuple = ()) -> None:
    """Trace and compile what `call_exported(name, fn, args, static=static)` will
    run, in a background thread, and return at once; that call then waits for it and
    runs the compiled program. `args` only need the call's structure, shapes and
    dtypes (and its non-array leaves).

    A fit that needs several programs (the calibration's residuals and solver)
    compiles the next one while this thread traces, prepares data and runs the
    current one. (XLA's CPU compiler already keeps ~1.7 of 2 cores busy with one
    program — measured 2026-11-29 — so two compilations at once gain little; the
    overlap with this thread's Python is what this buys.) Only with the cache on
    (the traced program is kept on disk, so a second process loads both) and on one
    device; the thread sees this thread's float64 setting. Any failure is left for
    `call_exported`, which then compiles as usual.
    """
    folder = _exported_folder()
    if folder is None:
        return
    key, _, specs, treedef, kept = _signature(name, fn, args, static, None)
    if key in _COMPILED or key in _PREPARING:
        return
    x64 = bool(jax.config.jax_enable_x64)  # (a thread-local setting)

    def compile_it():
        with jax.enable_x64(x64):
            exp = _exported(folder, key, fn, treedef, kept, specs)
            return None if exp is None else jax.jit(exp.call).lower(*specs).compile()

    _PREPARING[key] = _background().submit(compile_it)


def _exported_folder() -> Path | None:
    """Where traced programs are kept, or None when they are not (the cache off, a
    multi-process run, no serializer): then kernels are called directly."""
    if not _ENABLED or jax.process_count() > 1 or not _serialization_available():
        return None
    return _ENABLED[0] / "exported"


def _exported(folder: Path, key: str, fn, treedef, kept, specs):
    """The traced program of `key` (this process's, else stored, else a new export);
    None when exporting failed (the caller then runs `fn` itself)."""
    if key not in _EXPORTED:
        path = folder / f"{key}.bin"
        _EXPORTED[key] = _load_or_export(path, fn, treedef, kept, specs)
    return _EXPORTED[key]


_COMPILED: dict[str, object] = {}  # key -> compiled program (prepare_exported)
_MAX_COMPILED = 8  # (a calibration prepares two programs per fit)
_PREPARING: dict = {}  # key -> Future of the compiled program
_POOL: list = []


def _background():
    """The one background thread that compiles (created on first use)."""
    if not _POOL:
        from concurrent.futures import ThreadPoolExecutor

        _POOL.append(ThreadPoolExecutor(max_workers=1, thread_name_prefix="evhsi-compile"))
    return _POOL[0]


def _signature(name, fn, args, static, mesh):
    """`call_exported`'s key for `args` and what its program is called with: `(key,
    array leaves, their specs, the arguments' treedef, the non-array leaves)`."""
    # Flattened by hand: `eqx.partition` rebuilds each node around placeholder leaves,
    # which a registered dataclass's type-checked __init__ may refuse.
    every, treedef = jtu.tree_flatten(args)
    is_input = [eqx.is_array(a) for a in every]
    leaves = [a for a, d in zip(every, is_input) if d]
    kept = [None if d else a for a, d in zip(every, is_input)]
    if mesh is not None:
        from jax.sharding import NamedSharding
        from jax.sharding import PartitionSpec as P

        rep = NamedSharding(mesh, P())
        leaves = [
            a
            if isinstance(a, jax.Array) and len(a.sharding.device_set) > 1
            else jax.device_put(a, rep)
            for a in leaves
        ]
    specs = [
        jax.ShapeDtypeStruct(
            a.shape, a.dtype, sharding=a.sharding if mesh is not None else None
        )
        for a in leaves
    ]
    devices = repr(dict(mesh.shape)) if mesh is not None else 1
    parts = (
        name,
        repr(static),
        str(treedef),
        repr(kept),
        [
            (s.shape, str(s.dtype), str(getattr(s.sharding, "spec", None)))
            for s in specs
        ],
        devices,
        jax.default_backend(),
        jax.__version__,
        bool(jax.config.jax_enable_x64),
        _source_digest(),
    )
    key = f"{name}-{hashlib.sha256(repr(parts).encode()).hexdigest()[:32]}"
    return key, leaves, specs, treedef, kept


def _load_or_export(path: Path, fn, treedef, kept, specs):
    """The stored program at `path`, or a new export of `fn` written there; None when
    neither works (the caller then runs `fn` itself)."""
    try:
        return jax.export.deserialize(bytearray(path.read_bytes()))
    except Exception:  # missing, damaged or foreign: export (again, over it)
        pass

    def flat(*leaves):
        it = iter(leaves)
        every = [next(it) if a is None else a for a in kept]
        return fn(*jtu.tree_unflatten(treedef, every))

    try:
        exp = jax.export.export(jax.jit(flat))(*specs)
        data = exp.serialize()
    except Exception:
        return None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda f: f.write(data))
    except (OSError, ValueError):
        pass  # a read-only cache folder: this process still uses the export
    return exp
