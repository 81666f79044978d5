"""Recordings sweep by sweep: per-sweep cubes, previews and images.

Public namespace `evhsi_jax.video`; the implementation lives in private modules."""

from ._render import cube_to_srgb as cube_to_srgb
from ._render import write_comparison_png as write_comparison_png
from ._render import write_png as write_png
from ._stream import StreamResult as StreamResult
from ._stream import iter_sweep_cubes as iter_sweep_cubes
from ._stream import load_sweep_index as load_sweep_index
from ._stream import reconstruct_sweeps as reconstruct_sweeps
from ._stream import sweep_file_name as sweep_file_name
from ._stream import write_preview_gif as write_preview_gif

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
