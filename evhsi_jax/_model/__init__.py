"""Stage 1, the model: the rig (`Rig`, sensor effects), illumination band tables, the
event sensor (soft and exact triggering, photoreceptor), scenes and dynamic scenes, the
event container (`EventStream`) and the `Calibration` object."""

from ._calibration import Calibration as Calibration
from ._calibration import load_calibration as load_calibration
from ._dynamic import DYNAMIC_SCENES as DYNAMIC_SCENES
from ._dynamic import changed_pixels as changed_pixels
from ._dynamic import dynamic_scene as dynamic_scene
from ._dynamic import iridescent_reflectance as iridescent_reflectance
from ._dynamic import moving_chart as moving_chart
from ._dynamic import truth_cubes as truth_cubes
from ._event_stream import EventStream as EventStream
from ._event_stream import check_roi as check_roi
from ._illumination import BAND_TRIM as BAND_TRIM
from ._illumination import TABLE_STEP_NM as TABLE_STEP_NM
from ._illumination import BandTable as BandTable
from ._illumination import band_overlap as band_overlap
from ._illumination import band_table as band_table
from ._illumination import column_time_table as column_time_table
from ._illumination import fwhm_to_sigma as fwhm_to_sigma
from ._illumination import lookup as lookup
from ._illumination import lookup_tangents as lookup_tangents
from ._illumination import sampled_profile_overlap as sampled_profile_overlap
from ._illumination import sampled_profile_product as sampled_profile_product
from ._illumination import sweep_times_us as sweep_times_us
from ._illumination import trim_rows as trim_rows
from ._rig import COLUMN_SPREAD as COLUMN_SPREAD
from ._rig import SENSOR_PRESETS as SENSOR_PRESETS
from ._rig import Rig as Rig
from ._rig import SensorEffects as SensorEffects
from ._scenes import BUILTIN_SCENES as BUILTIN_SCENES
from ._scenes import Scene as Scene
from ._scenes import load_scene as load_scene
from ._scenes import parse_size as parse_size
from ._sensor import exact_events_scan as exact_events_scan
from ._sensor import initial_state as initial_state
from ._sensor import photoreceptor_lowpass as photoreceptor_lowpass
from ._sensor import soft_event_counts as soft_event_counts
