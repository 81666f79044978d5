"""Stage 0, shared base: atomic file writing and storage helpers, spectral grids and
resampling, reference spectra, metrics, hardware limits, the compilation cache and the
device-mesh plumbing (`shard`) and the switch between numba kernels and their NumPy
references (`numba_kernels`). Imports nothing else from the package."""

from . import _numba as numba_kernels  # noqa: F401  (compiled-kernel switch)
from . import _shard as shard  # noqa: F401  (the mesh plumbing as a namespace)
from ._cache import call_exported as call_exported
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._cache import prepare_exported as prepare_exported
from ._limits import check_fits as check_fits
from ._limits import release_free_memory as release_free_memory
from ._metrics import evaluate as evaluate
from ._metrics import per_label_table as per_label_table
from ._metrics import psnr_db as psnr_db
from ._metrics import rms as rms
from ._metrics import sam_deg as sam_deg
from ._metrics import sam_map_deg as sam_map_deg
from ._metrics import ssim as ssim
from ._numba import njit as njit
from ._numba import numba_available as numba_available
from ._numba import readonly as readonly
from ._numba import use_numba as use_numba
from ._reference_spectra import reference_spectra as reference_spectra
from ._shard import initialize_distributed as initialize_distributed
from ._shard import is_main_process as is_main_process
from ._shard import pixel_mesh as pixel_mesh
from ._sorting import stable_argsort_int as stable_argsort_int
from ._spectra import SpectralGrid as SpectralGrid
from ._spectra import band_integrate as band_integrate
from ._spectra import band_integrate_matrix as band_integrate_matrix
from ._spectra import default_camera_response as default_camera_response
from ._spectra import default_lamp_spectrum as default_lamp_spectrum
from ._spectra import resample as resample
from ._spectra import resample_matrix as resample_matrix
from ._storage import TEMP_SUFFIX as TEMP_SUFFIX
from ._storage import atomic_write as atomic_write
from ._storage import check_outputs as check_outputs
from ._storage import one_line as one_line
from ._storage import read_npz as read_npz
from ._storage import same_file as same_file
from ._storage import scalar_int as scalar_int
