"""Stage 5, sweep-by-sweep products: per-sweep reconstruction of recordings (also
live), cube folders and video stores, previews and the browser viewer."""

from ._store import holds_video as holds_video
from ._store import is_video_store as is_video_store
from ._stream import StreamResult as StreamResult
from ._stream import convert_sweeps as convert_sweeps
from ._stream import iter_sweep_cubes as iter_sweep_cubes
from ._stream import load_sweep_index as load_sweep_index
from ._stream import reconstruct_sweeps as reconstruct_sweeps
from ._stream import sweep_file_name as sweep_file_name
from ._stream import wait_for_file as wait_for_file
from ._stream import write_preview_gif as write_preview_gif
from ._viewer import CubeSource as CubeSource
from ._viewer import make_server as make_server
