"""Recordings sweep by sweep: per-sweep cubes, previews and images.

Public namespace `evhsi_jax.video`; the implementation lives in private modules."""

from ._io import cube_to_srgb as cube_to_srgb
from ._io import write_comparison_png as write_comparison_png
from ._io import write_png as write_png
from ._video import StreamResult as StreamResult
from ._video import iter_sweep_cubes as iter_sweep_cubes
from ._video import load_sweep_index as load_sweep_index
from ._video import reconstruct_sweeps as reconstruct_sweeps
from ._video import sweep_file_name as sweep_file_name
from ._video import write_preview_gif as write_preview_gif

__all__ = [
    "reconstruct_sweeps",
    "iter_sweep_cubes",
    "load_sweep_index",
    "sweep_file_name",
    "StreamResult",
    "write_preview_gif",
    "write_png",
    "write_comparison_png",
    "cube_to_srgb",
]
