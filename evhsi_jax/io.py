"""Event files (npz, Prophesee EVT 2.0/3.0 .raw), sweeps, bandwidth, cube files.

Public namespace `evhsi_jax.io`; the implementation lives in private modules."""

from ._io import DecodeError as DecodeError
from ._io import DecodeReport as DecodeReport
from ._io import EventReader as EventReader
from ._io import Sweeps as Sweeps
from ._io import bandwidth_summary as bandwidth_summary
from ._io import convert_events as convert_events
from ._io import describe_events as describe_events
from ._io import estimate_sweep_phase as estimate_sweep_phase
from ._io import evt3_bytes as evt3_bytes
from ._io import frame_bytes as frame_bytes
from ._io import iter_events as iter_events
from ._io import load_cube as load_cube
from ._io import nominal_event_bytes as nominal_event_bytes
from ._io import read_events as read_events
from ._io import read_events_window as read_events_window
from ._io import replay_raw as replay_raw
from ._io import save_cube as save_cube
from ._io import split_sweeps as split_sweeps
from ._io import write_events as write_events
from ._io import write_evt3 as write_evt3
from ._model import EventStream as EventStream

__all__ = [
    "EventReader",
    "replay_raw",
    "write_evt3",
    "EventStream",
    "read_events",
    "write_events",
    "iter_events",
    "read_events_window",
    "convert_events",
    "describe_events",
    "evt3_bytes",
    "DecodeError",
    "DecodeReport",
    "Sweeps",
    "split_sweeps",
    "estimate_sweep_phase",
    "bandwidth_summary",
    "nominal_event_bytes",
    "frame_bytes",
    "load_cube",
    "save_cube",
]
