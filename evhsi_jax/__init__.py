"""evhsi_jax: event-based active hyperspectral imaging in JAX.

Forward model (rainbow illumination, camera response, event triggering — exact and
soft), event files, per-pixel box-QP reconstruction, metrics and rendering. The public
API is re-exported here; implementation lives in private modules.
"""

from ._baselines import (
    CassiOperator as CassiOperator,
)
from ._baselines import (
    FrameOperator as FrameOperator,
)
from ._baselines import (
    FrameStack as FrameStack,
)
from ._baselines import (
    PatchConfig as PatchConfig,
)
from ._baselines import (
    SpectralBasis as SpectralBasis,
)
from ._baselines import (
    basis_project as basis_project,
)
from ._baselines import (
    capture_frames as capture_frames,
)
from ._baselines import (
    cassi_measure as cassi_measure,
)
from ._baselines import (
    desci as desci,
)
from ._baselines import (
    gap_tv as gap_tv,
)
from ._baselines import (
    learn_basis as learn_basis,
)
from ._baselines import (
    matched_frame_count as matched_frame_count,
)
from ._baselines import (
    random_mask as random_mask,
)
from ._baselines import (
    reconstruct_frames as reconstruct_frames,
)
from ._baselines import (
    reflectance_basis as reflectance_basis,
)
from ._baselines import (
    training_reflectances as training_reflectances,
)
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._calibrate import (
    CalibrationResult as CalibrationResult,
)
from ._calibrate import (
    ChartData as ChartData,
)
from ._calibrate import (
    apply_spectral_correction as apply_spectral_correction,
)
from ._calibrate import (
    calibrate as calibrate,
)
from ._calibrate import (
    chart_data as chart_data,
)
from ._calibrate import (
    chart_log_steps as chart_log_steps,
)
from ._calibrate import (
    chart_residuals as chart_residuals,
)
from ._calibrate import (
    save_calibration as save_calibration,
)
from ._calibrate import (
    spectral_correction as spectral_correction,
)
from ._calibrate import (
    spectral_traces as spectral_traces,
)
from ._calibrate import (
    threshold_maps_from_chart as threshold_maps_from_chart,
)
from ._calibration import (
    Calibration as Calibration,
)
from ._calibration import (
    load_calibration as load_calibration,
)
from ._cubefile import load_cube as load_cube
from ._cubefile import save_cube as save_cube
from ._design import DesignLimits as DesignLimits
from ._design import DesignParams as DesignParams
from ._design import DesignProblem as DesignProblem
from ._design import DesignResult as DesignResult
from ._design import DesignSpace as DesignSpace
from ._design import constraint_values as constraint_values
from ._design import design_loss as design_loss
from ._design import design_problem as design_problem
from ._design import design_value_and_grad as design_value_and_grad
from ._design import evaluate_design as evaluate_design
from ._design import optimise_design as optimise_design
from ._design import save_trajectory as save_trajectory
from ._design import training_scene as training_scene
from ._design import training_spectra as training_spectra
from ._dynamic import DYNAMIC_SCENES as DYNAMIC_SCENES
from ._dynamic import changed_pixels as changed_pixels
from ._dynamic import dynamic_scene as dynamic_scene
from ._dynamic import iridescent_reflectance as iridescent_reflectance
from ._dynamic import moving_chart as moving_chart
from ._dynamic import truth_cubes as truth_cubes
from ._events import EventStream as EventStream
from ._illumination import (
    BandTable as BandTable,
)
from ._illumination import (
    band_table as band_table,
)
from ._illumination import (
    column_time_table as column_time_table,
)
from ._illumination import (
    fwhm_to_sigma as fwhm_to_sigma,
)
from ._illumination import (
    lookup as lookup,
)
from ._illumination import (
    sweep_times_us as sweep_times_us,
)
from ._io import (
    DecodeError as DecodeError,
)
from ._io import (
    DecodeReport as DecodeReport,
)
from ._io import (
    Sweeps as Sweeps,
)
from ._io import (
    bandwidth_summary as bandwidth_summary,
)
from ._io import (
    convert_events as convert_events,
)
from ._io import (
    describe_events as describe_events,
)
from ._io import (
    estimate_sweep_phase as estimate_sweep_phase,
)
from ._io import (
    evt3_bytes as evt3_bytes,
)
from ._io import (
    frame_bytes as frame_bytes,
)
from ._io import (
    iter_events as iter_events,
)
from ._io import (
    nominal_event_bytes as nominal_event_bytes,
)
from ._io import (
    read_events as read_events,
)
from ._io import (
    read_events_window as read_events_window,
)
from ._io import (
    split_sweeps as split_sweeps,
)
from ._io import (
    write_events as write_events,
)
from ._metrics import (
    evaluate as evaluate,
)
from ._metrics import (
    per_label_table as per_label_table,
)
from ._metrics import (
    psnr_db as psnr_db,
)
from ._metrics import (
    rms as rms,
)
from ._metrics import (
    sam_deg as sam_deg,
)
from ._metrics import (
    sam_map_deg as sam_map_deg,
)
from ._metrics import (
    ssim as ssim,
)
from ._reconstruct import (
    SOLVERS as SOLVERS,
)
from ._reconstruct import (
    ProblemConfig as ProblemConfig,
)
from ._reconstruct import (
    ReconstructionInfo as ReconstructionInfo,
)
from ._reconstruct import (
    SolverSpec as SolverSpec,
)
from ._reconstruct import (
    kkt_residual as kkt_residual,
)
from ._reconstruct import (
    pixel_system as pixel_system,
)
from ._reconstruct import (
    reconstruct as reconstruct,
)
from ._reconstruct import (
    solver_spec as solver_spec,
)
from ._reconstruct import (
    spectral_prior_matrix as spectral_prior_matrix,
)
from ._render import (
    cube_to_srgb as cube_to_srgb,
)
from ._render import (
    write_comparison_png as write_comparison_png,
)
from ._render import (
    write_png as write_png,
)
from ._rig import SENSOR_PRESETS as SENSOR_PRESETS
from ._rig import Rig as Rig
from ._rig import SensorEffects as SensorEffects
from ._scenes import BUILTIN_SCENES as BUILTIN_SCENES
from ._scenes import Scene as Scene
from ._scenes import load_scene as load_scene
from ._scenes import parse_size as parse_size
from ._sensor import exact_events_scan as exact_events_scan
from ._sensor import soft_event_counts as soft_event_counts
from ._shard import initialize_distributed as initialize_distributed
from ._shard import is_main_process as is_main_process
from ._shard import pixel_mesh as pixel_mesh
from ._simulate import (
    SimulationInfo as SimulationInfo,
)
from ._simulate import (
    simulate as simulate,
)
from ._simulate import (
    threshold_maps as threshold_maps,
)
from ._spectra import (
    SpectralGrid as SpectralGrid,
)
from ._spectra import (
    band_integrate as band_integrate,
)
from ._spectra import (
    default_camera_response as default_camera_response,
)
from ._spectra import (
    default_lamp_spectrum as default_lamp_spectrum,
)
from ._spectra import (
    resample as resample,
)
from ._stream import StreamResult as StreamResult
from ._stream import iter_sweep_cubes as iter_sweep_cubes
from ._stream import load_sweep_index as load_sweep_index
from ._stream import reconstruct_sweeps as reconstruct_sweeps
from ._stream import sweep_file_name as sweep_file_name
from ._stream import write_preview_gif as write_preview_gif

__version__ = "0.1.0"
