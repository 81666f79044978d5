"""The forward model: rig, spectra, scenes, illumination, sensor, simulator.

Public namespace `evhsi_jax.forward`; the implementation lives in private modules."""

from ._dynamic import DYNAMIC_SCENES as DYNAMIC_SCENES
from ._dynamic import changed_pixels as changed_pixels
from ._dynamic import dynamic_scene as dynamic_scene
from ._dynamic import iridescent_reflectance as iridescent_reflectance
from ._dynamic import moving_chart as moving_chart
from ._dynamic import truth_cubes as truth_cubes
from ._illumination import BandTable as BandTable
from ._illumination import band_table as band_table
from ._illumination import column_time_table as column_time_table
from ._illumination import fwhm_to_sigma as fwhm_to_sigma
from ._illumination import lookup as lookup
from ._illumination import sweep_times_us as sweep_times_us
from ._rig import SENSOR_PRESETS as SENSOR_PRESETS
from ._rig import Rig as Rig
from ._rig import SensorEffects as SensorEffects
from ._scenes import BUILTIN_SCENES as BUILTIN_SCENES
from ._scenes import Scene as Scene
from ._scenes import load_scene as load_scene
from ._scenes import parse_size as parse_size
from ._sensor import exact_events_scan as exact_events_scan
from ._sensor import soft_event_counts as soft_event_counts
from ._simulate import SimulationInfo as SimulationInfo
from ._simulate import simulate as simulate
from ._simulate import threshold_maps as threshold_maps
from ._spectra import SpectralGrid as SpectralGrid
from ._spectra import band_integrate as band_integrate
from ._spectra import default_camera_response as default_camera_response
from ._spectra import default_lamp_spectrum as default_lamp_spectrum
from ._spectra import resample as resample

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
