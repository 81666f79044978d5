"""numba kernel of :mod:`._sorting` (imported on first use). Marked `no_type_check` so
that the jaxtyping import hook of the test suite leaves it to numba."""

from __future__ import annotations

from typing import no_type_check

import numpy as np

from ._numba import njit


@njit
@no_type_check
def counting_order(keys, lo, n_keys):
    """The stable sorting permutation of `keys` (all in `[lo, lo + n_keys)`)."""
    start = np.zeros(n_keys + 1, np.int64)
    for i in range(keys.size):
        start[keys[i] - lo + 1] += 1
    for k in range(n_keys):
        start[k + 1] += start[k]
    order = np.empty(keys.size, np.int64)
    for i in range(keys.size):
        k = keys[i] - lo
        order[start[k]] = i
        start[k] += 1
    return order
