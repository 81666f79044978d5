"""Test configuration: strict dtype promotion, shared data location, small fixtures.

Tests run in float32 (the library default); float64 checks wrap their body in
`with jax.enable_x64(True):` and build their inputs inside it.

The persistent compilation cache is on for this process and, through
`EVHSI_CACHE_DIR`, for every `evhsi` subprocess a test starts: a kernel compiled once
serves them all (the user's cache folder unless EVHSI_CACHE_DIR says otherwise; set it
to `off` to test without).
"""

import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_numpy_dtype_promotion", "strict")

from evhsi_jax._base._cache import cache_dir, enable_compilation_cache  # noqa: E402

# One XLA host device for this process and every `evhsi` subprocess a test starts:
# `evhsi reconstruct` would otherwise ask for one per core (its default `--devices`)
# and compile the sharded kernels once more in every subprocess (~10 % of the CLI
# tests' time with an empty cache). A device count already in XLA_FLAGS wins there, as
# here; the sharded path has its own tests (reconstruction/test_shard.py, 4 devices in
# a subprocess) and the contract checks run the CLI with its defaults. JAX's backend
# starts now, so nothing depends on which test starts it first.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=1"
    ).strip()
jax.devices()

if cache_dir() is not None:
    os.environ.setdefault("EVHSI_CACHE_DIR", str(cache_dir()))
enable_compilation_cache()


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
    from evhsi_jax._base import _numba as _jit

    if request.param == "numba" and not _jit.numba_available():
        pytest.skip("no numba")
    with _jit.use_backend(request.param):
        yield request.param


# Modules that take minutes (calibration fits, design gradients, notebooks): run them
# first, so that with pytest-xdist (`make test`: `-n 2 --dist loadfile`) the short
# modules fill the other worker instead of one long module ending the run alone.
HEAVY_FIRST = (
    "test_band_fit.py",
    "test_realism_fit.py",
    "test_realism_calibration.py",
    "test_design.py",
    "test_notebooks.py",
    "test_calibrate.py",
    "test_reconstruct.py",
    "test_fit_blocks.py",
    "test_cuda_kernel.py",
    "test_shard.py",
    "test_reliability.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


# The fused reconstruction's numba kernel takes ~95 s of one core to compile on a 2-core
# machine (2026-12-08), once per install. With an empty cache (a fresh clone: CI) the
# heavy modules above reach their first reconstruction on both workers at about the
# same time, and one waits on the other's compile lock (`_base._numba`) with its core
# idle. Under pytest-xdist the controller starts one small reconstruction in a
# background process as the session starts: the kernel compiles while the workers run
# their calibrations, and they load it from numba's cache. Nothing depends on it: a
# worker that needs the kernel first waits for the lock as before, or compiles it
# itself if the process failed.
_WARM = (
    "import jax.random as jr, evhsi_jax as ev; s = ev.load_scene('tcs', (4, 6)); "
    "ev.reconstruct(ev.simulate(s, ev.Rig(), sweeps=1, key=jr.key(0)), ev.Rig())"
)
_warm_process = None


def _kernel_cache_is_current() -> bool:
    """Whether numba's cache beside the fused kernel looks newer than its source (a
    heuristic: a stale or foreign entry only costs the background process)."""
    import evhsi_jax._reconstruct as rec

    src = Path(rec.__file__).parent / "_fused_jit.py"
    index = list((src.parent / "__pycache__").glob("_fused_jit.solve_pixels-*.nbi"))
    return any(p.stat().st_mtime >= src.stat().st_mtime for p in index)


def pytest_sessionstart(session):
    global _warm_process
    config = session.config
    if hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", 0):
        return  # an xdist worker, or no workers
    if os.environ.get("EVHSI_NO_NUMBA") or os.environ.get("NUMBA_CACHE_DIR"):
        return
    if _kernel_cache_is_current():
        return
    import subprocess
    import sys

    _warm_process = subprocess.Popen(
        [sys.executable, "-c", _WARM],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


def pytest_sessionfinish(session):
    if _warm_process is not None and _warm_process.poll() is None:
        _warm_process.kill()
        _warm_process.wait()
