"""Sizes checked against what this machine can hold, before anything is allocated.

A user's typo (a 65536×65536 header, `--sweeps 1000000000000`) must end in one clear
line, not in a `MemoryError` half-way through or the kernel killing the process. The
estimates here are deliberately rough (within a small factor of the real peak) and
only refuse what cannot fit.
"""

from __future__ import annotations

import os

__all__ = ["available_memory_bytes", "check_fits", "release_free_memory"]


def available_memory_bytes() -> int:
    """Memory this process may use: `MemAvailable` of /proc/meminfo where there is
    one, else the physical memory (an over-estimate, so nothing valid is refused)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - exotic OS
        return 1 << 62


def check_fits(nbytes: float, what: str) -> None:
    """Raise `ValueError` when `what` needs more than the memory available."""
    avail = available_memory_bytes()
    if nbytes > avail:
        raise ValueError(
            f"{what} needs about {nbytes / 1e9:,.1f} GB of memory, more than the "
            f"{avail / 1e9:,.1f} GB available"
        )


def release_free_memory() -> bool:
    """Hand the C heap's free pages back to the system (glibc's `malloc_trim`).

    XLA's compiler allocates and frees hundreds of MB through `malloc`, and glibc keeps
    the freed memory in its arenas: a calibration's first run (which compiles) held
    ~0.5 GB of it when its per-pixel threshold maps began, and those maps' own peak
    came on top (1.97 GB in-process, against 1.71 GB after this call; 2026-11-27).
    Costs milliseconds; returns False where there is no glibc (nothing changes)."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    trim(0)
    return True
