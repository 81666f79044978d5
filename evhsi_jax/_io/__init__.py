"""Stage 3, files: events in, cubes and pictures out.

Events: Prophesee EVT 3.0 `.raw` (read and write), EVT 2.0 `.raw` (read) and the `.npz` layout
of DESIGN.md; bounded-memory streaming and time-window reads; sweep segmentation;
bandwidth accounting. Cubes: `.npz`, ENVI and Zarr (`_cubefile`); pictures: sRGB
renderings and PNGs (`_render`). See each module's docstring for the format decisions. The hot
loops run as numba kernels by default, with the vectorised NumPy code as reference and
fallback (`EVHSI_NO_NUMBA=1`; see `_base/_numba`).
"""

from ._bandwidth import bandwidth_summary as bandwidth_summary
from ._bandwidth import evt3_bytes as evt3_bytes
from ._bandwidth import frame_bytes as frame_bytes
from ._bandwidth import nominal_event_bytes as nominal_event_bytes
from ._cubefile import CUBE_SUFFIXES as CUBE_SUFFIXES
from ._cubefile import load_cube as load_cube
from ._cubefile import save_cube as save_cube
from ._evt3_encode import encode_evt3_words as encode_evt3_words
from ._evt3_encode import evt3_word_count as evt3_word_count
from ._evt3_encode import write_evt3 as write_evt3
from ._files import convert_events as convert_events
from ._files import describe_events as describe_events
from ._files import replay_raw as replay_raw
from ._files import write_events as write_events
from ._header import RawHeader as RawHeader
from ._header import parse_header as parse_header
from ._reader import DEFAULT_CHUNK_BYTES as DEFAULT_CHUNK_BYTES
from ._reader import EventReader as EventReader
from ._reader import iter_events as iter_events
from ._reader import open_events as open_events
from ._reader import read_events as read_events
from ._reader import read_events_window as read_events_window
from ._render import cube_to_srgb as cube_to_srgb
from ._render import write_comparison_png as write_comparison_png
from ._render import write_png as write_png
from ._report import DecodeError as DecodeError
from ._report import DecodeReport as DecodeReport
from ._sweeps import SweepCutter as SweepCutter
from ._sweeps import Sweeps as Sweeps
from ._sweeps import estimate_sweep_phase as estimate_sweep_phase
from ._sweeps import split_sweeps as split_sweeps
