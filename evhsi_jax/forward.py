"""The forward model: rig, spectra, scenes, illumination, sensor, simulator.

Public namespace `evhsi_jax.forward`; the implementation lives in private modules."""

from ._base import SpectralGrid as SpectralGrid
from ._base import band_integrate as band_integrate
from ._base import default_camera_response as default_camera_response
from ._base import default_lamp_spectrum as default_lamp_spectrum
from ._base import resample as resample
from ._base import resample_matrix as resample_matrix
from ._model import BUILTIN_SCENES as BUILTIN_SCENES
from ._model import DYNAMIC_SCENES as DYNAMIC_SCENES
from ._model import SENSOR_PRESETS as SENSOR_PRESETS
from ._model import BandTable as BandTable
from ._model import Rig as Rig
from ._model import Scene as Scene
from ._model import SensorEffects as SensorEffects
from ._model import band_table as band_table
from ._model import changed_pixels as changed_pixels
from ._model import column_time_table as column_time_table
from ._model import dynamic_scene as dynamic_scene
from ._model import exact_events_scan as exact_events_scan
from ._model import fwhm_to_sigma as fwhm_to_sigma
from ._model import iridescent_reflectance as iridescent_reflectance
from ._model import load_scene as load_scene
from ._model import lookup as lookup
from ._model import moving_chart as moving_chart
from ._model import parse_size as parse_size
from ._model import soft_event_counts as soft_event_counts
from ._model import sweep_times_us as sweep_times_us
from ._model import truth_cubes as truth_cubes
from ._simulate import SimulationInfo as SimulationInfo
from ._simulate import simulate as simulate
from ._simulate import threshold_maps as threshold_maps

__all__ = [
    "Rig",
    "SensorEffects",
    "SENSOR_PRESETS",
    "SpectralGrid",
    "Scene",
    "BUILTIN_SCENES",
    "load_scene",
    "parse_size",
    "band_integrate",
    "resample",
    "resample_matrix",
    "default_camera_response",
    "default_lamp_spectrum",
    "BandTable",
    "band_table",
    "column_time_table",
    "fwhm_to_sigma",
    "lookup",
    "sweep_times_us",
    "exact_events_scan",
    "soft_event_counts",
    "simulate",
    "SimulationInfo",
    "threshold_maps",
    "DYNAMIC_SCENES",
    "changed_pixels",
    "dynamic_scene",
    "iridescent_reflectance",
    "moving_chart",
    "truth_cubes",
]
