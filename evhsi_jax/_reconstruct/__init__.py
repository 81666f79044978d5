"""Per-pixel box-QP reconstruction of spectra from events."""

from ._deblur import DEFAULT_WIENER_REG as DEFAULT_WIENER_REG
from ._deblur import deblur_cube as deblur_cube
from ._implicit import box_qp as box_qp
from ._implicit import reconstruct_pixels as reconstruct_pixels
from ._pipeline import SOLVERS as SOLVERS
from ._pipeline import ReconstructionInfo as ReconstructionInfo
from ._pipeline import SolverSpec as SolverSpec
from ._pipeline import batch_sizes as batch_sizes
from ._pipeline import noise_model as noise_model
from ._pipeline import reconstruct as reconstruct
from ._pipeline import screen_events as screen_events
from ._pipeline import solver_spec as solver_spec
from ._pixels import TIMESTAMP_CENTRE_US as TIMESTAMP_CENTRE_US
from ._pixels import PixelBatch as PixelBatch
from ._pixels import PixelEvents as PixelEvents
from ._pixels import group_pixels as group_pixels
from ._problem import ProblemConfig as ProblemConfig
from ._problem import lit_interval_us as lit_interval_us
from ._problem import pixel_system as pixel_system
from ._problem import spectral_prior_matrix as spectral_prior_matrix
from ._solvers import active_set as active_set
from ._solvers import active_set_batch as active_set_batch
from ._solvers import apg as apg
from ._solvers import kkt_residual as kkt_residual
from ._solvers import svd_nullvector as svd_nullvector
from ._sweep_speed import warp_times as warp_times
