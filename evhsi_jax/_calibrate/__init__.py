"""Stage 5, calibration from gray-chart captures: chart data, the joint optimistix fit
of the rig, per-pixel threshold maps and the sensor noise it can measure."""

from ._chart import ChartData as ChartData
from ._chart import ChartSpeeds as ChartSpeeds
from ._chart import chart_data as chart_data
from ._chart import chart_log_steps as chart_log_steps
from ._chart import chart_residuals as chart_residuals
from ._chart import chart_sweep_speeds as chart_sweep_speeds
from ._chart import spectral_traces as spectral_traces
from ._chart import sweep_first_events as sweep_first_events
from ._chart import threshold_maps_from_chart as threshold_maps_from_chart
from ._fit import CalibrationResult as CalibrationResult
from ._fit import apply_spectral_correction as apply_spectral_correction
from ._fit import calibrate as calibrate
from ._fit import save_calibration as save_calibration
from ._fit import spectral_correction as spectral_correction
