"""evhsi_jax: event-based active hyperspectral imaging in JAX.

The top level holds the verbs of the pipeline (simulate → calibrate → reconstruct →
evaluate → render) and the objects they pass around; everything else is in a public
namespace, each re-exported from private implementation modules:

- `evhsi_jax.forward` — rig, spectra, scenes, illumination, sensor, simulator
- `evhsi_jax.io` — event files, sweeps, bandwidth, cube files
- `evhsi_jax.reconstruction` — the per-pixel box-QP and its parts
- `evhsi_jax.calibration` — gray-chart calibration
- `evhsi_jax.video` — recordings sweep by sweep, previews
- `evhsi_jax.design` — optical design by gradients
- `evhsi_jax.baselines` — frame-based and CASSI baselines
- `evhsi_jax.sharding` — devices and hosts
- `evhsi_jax.metrics` — SAM, PSNR, SSIM, per-patch tables
"""

from . import forward as forward
from . import io as io
from . import metrics as metrics
from . import reconstruction as reconstruction
from . import sharding as sharding
from . import video as video
from ._base import enable_compilation_cache as enable_compilation_cache
from ._base import evaluate as evaluate
from ._io import cube_to_srgb as cube_to_srgb
from ._io import load_cube as load_cube
from ._io import read_events as read_events
from ._io import save_cube as save_cube
from ._io import write_events as write_events
from ._io import write_png as write_png
from ._model import Calibration as Calibration
from ._model import EventStream as EventStream
from ._model import Rig as Rig
from ._model import Scene as Scene
from ._model import load_calibration as load_calibration
from ._model import load_scene as load_scene
from ._reconstruct import reconstruct as reconstruct
from ._simulate import simulate as simulate
from ._video import reconstruct_sweeps as reconstruct_sweeps

__version__ = "0.1.0"

__all__ = [
    # objects
    "Rig", "Scene", "EventStream", "Calibration",
    # verbs
    "load_scene", "read_events", "write_events", "load_cube", "save_cube",
    "load_calibration", "save_calibration", "simulate", "calibrate", "reconstruct",
    "reconstruct_sweeps", "evaluate", "write_png", "cube_to_srgb",
    "enable_compilation_cache",
    # namespaces
    "forward", "io", "reconstruction", "calibration", "video", "design", "baselines",
    "sharding", "metrics",
]  # fmt: skip

_NAMESPACES = (
    "forward", "io", "reconstruction", "calibration", "video", "design", "baselines",
    "sharding", "metrics",
)  # fmt: skip


# Imported on first use (~0.6 s off every start that does not need them; calibration
# brings optimistix and lineax).
_LAZY = ("design", "baselines", "calibration")
_LAZY_VERBS = {"calibrate": "._calibrate", "save_calibration": "._calibrate"}


def __getattr__(name):
    import importlib

    if name in _LAZY:
        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY_VERBS:
        return getattr(importlib.import_module(_LAZY_VERBS[name], __name__), name)
    # A name that left the top level: say where it is now, in one line.
    for ns in _NAMESPACES:
        if name in getattr(importlib.import_module(f".{ns}", __name__), "__all__"):
            raise AttributeError(f"evhsi_jax.{name} is now evhsi_jax.{ns}.{name}")
    raise AttributeError(f"module 'evhsi_jax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY) | set(_LAZY_VERBS))
