"""A persistent compilation cache, so a command's second run starts in seconds.

Most of a short command's time is XLA compiling the same kernels again. JAX can keep
compiled executables on disk (its persistent compilation cache, keyed by the program,
the shapes, the JAX/XLA versions and flags, so a stale entry is never used). The `evhsi`
command turns it on; a Python user calls :func:`enable_compilation_cache` (importing
the library changes no global JAX setting).

Where: `$EVHSI_CACHE_DIR` if set (`off` turns the cache off), else
`$XDG_CACHE_HOME/evhsi_jax/jax` (default `~/.cache/evhsi_jax/jax`). The folder is safe
to delete at any time; JAX fills it again as needed.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["enable_compilation_cache", "cache_dir"]

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
