"""Test configuration: strict dtype promotion, shared data location, small fixtures.

Tests run in float32 (the library default); float64 checks wrap their body in
`with jax.enable_x64(True):` and build their inputs inside it.
"""

import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_numpy_dtype_promotion", "strict")


def shared_data_dir() -> Path | None:
    """`../shared/data` beside the checkout, or $EVHSI_SHARED_DATA; None if absent."""
    env = os.environ.get("EVHSI_SHARED_DATA")
    cand = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    return cand if cand.is_dir() else None


@pytest.fixture(scope="session")
def shared_data():
    d = shared_data_dir()
    if d is None:
        pytest.skip("../shared/data is absent")
    return d


@pytest.fixture(scope="module", params=["numba", "numpy"])
def io_backend(request):
    """Run a module's event-file tests with the numba kernels and the NumPy reference
    (`pytestmark = pytest.mark.usefixtures("io_backend")`)."""
    from evhsi_jax._io import _jit

    if request.param == "numba" and not _jit.numba_available():
        pytest.skip("no numba")
    with _jit.use_backend(request.param):
        yield request.param
