"""Measured spectra the package uses at every start, kept as package data.

The xenon lamp of the default rig (Kinoton 75P) and the ColorChecker (N Ohta) come
from colour-science's datasets (BSD-3-Clause). Importing `colour` takes ~2 s (it loads
its plotting stack), which every `Rig()` paid for the lamp; the arrays are therefore
stored in `reference_spectra.npz` beside this module, written by
`python -m evhsi_jax._base._reference_spectra` from the installed colour-science, and
`tests/forward/test_spectra.py` checks they still equal colour's values.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np

PATH = Path(__file__).with_name("reference_spectra.npz")


def from_colour() -> dict[str, np.ndarray]:
    """The same arrays, taken from colour-science now (slow: imports `colour`)."""
    import colour

    lamp = colour.SDS_LIGHT_SOURCES["Kinoton 75P"]
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    names = list(sds.keys())
    return {
        "lamp_wavelengths_nm": np.asarray(lamp.wavelengths, np.float64),
        "lamp_values": np.asarray(lamp.values, np.float64),
        "colorchecker_names": np.asarray(names),
        "colorchecker_wavelengths_nm": np.asarray(sds[names[0]].wavelengths, np.float64),
        "colorchecker_values": np.stack(
            [np.asarray(sds[k].values, np.float64) for k in names]
        ),
    }


@functools.lru_cache(maxsize=1)
def reference_spectra() -> dict[str, np.ndarray]:
    """The stored arrays (see the module docstring)."""
    with np.load(PATH) as f:
        return {k: f[k] for k in f.files}


if __name__ == "__main__":  # regenerate the package data from colour-science
    np.savez_compressed(PATH, **from_colour())
    print(f"wrote {PATH}", file=sys.stderr)
