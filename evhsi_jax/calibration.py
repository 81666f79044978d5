"""Calibration from gray-chart captures and the Calibration object.

Public namespace `evhsi_jax.calibration`; the implementation lives in private modules."""

from ._calibrate import CalibrationResult as CalibrationResult
from ._calibrate import ChartData as ChartData
from ._calibrate import ChartSpeeds as ChartSpeeds
from ._calibrate import apply_spectral_correction as apply_spectral_correction
from ._calibrate import calibrate as calibrate
from ._calibrate import chart_data as chart_data
from ._calibrate import chart_log_steps as chart_log_steps
from ._calibrate import chart_residuals as chart_residuals
from ._calibrate import chart_sweep_speeds as chart_sweep_speeds
from ._calibrate import save_calibration as save_calibration
from ._calibrate import spectral_correction as spectral_correction
from ._calibrate import spectral_traces as spectral_traces
from ._calibrate import sweep_first_events as sweep_first_events
from ._calibrate import threshold_maps_from_chart as threshold_maps_from_chart
from ._model import Calibration as Calibration
from ._model import load_calibration as load_calibration

__all__ = [
    "calibrate",
    "Calibration",
    "CalibrationResult",
    "load_calibration",
    "save_calibration",
    "ChartData",
    "chart_data",
    "chart_log_steps",
    "chart_residuals",
    "chart_sweep_speeds",
    "ChartSpeeds",
    "spectral_traces",
    "sweep_first_events",
    "threshold_maps_from_chart",
    "spectral_correction",
    "apply_spectral_correction",
]
