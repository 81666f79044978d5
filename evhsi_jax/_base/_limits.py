"""Sizes checked against what this machine can hold, before anything is allocated.

A user's typo (a 65536×65536 header, `--sweeps 1000000000000`) must end in one clear
line, not in a `MemoryError` half-way through or the kernel killing the process. The
estimates here are deliberately rough (within a small factor of the real peak) and
only refuse what cannot fit.
"""

from __future__ import annotations

import os

__all__ = ["available_memory_bytes", "check_fits"]


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
