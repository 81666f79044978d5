"""Baselines the event-based system is compared with (paper supplement 6.5, 7.1–7.3).

- a frame camera under the same sweeping rainbow (full bandwidth or bandwidth-matched),
  reconstructed by least squares on the linearly interpolated intensity trace;
- a learned low-dimensional reflectance basis, evaluated as an oracle projection;
- single-disperser CASSI with GAP-TV and DeSCI reconstructions.
"""

from ._basis import SpectralBasis as SpectralBasis
from ._basis import basis_coefficients as basis_coefficients
from ._basis import basis_project as basis_project
from ._basis import learn_basis as learn_basis
from ._basis import reflectance_basis as reflectance_basis
from ._basis import training_reflectances as training_reflectances
from ._cassi import CassiOperator as CassiOperator
from ._cassi import cassi_measure as cassi_measure
from ._cassi import random_mask as random_mask
from ._desci import PatchConfig as PatchConfig
from ._desci import block_match as block_match
from ._desci import desci as desci
from ._desci import wnnm_denoise as wnnm_denoise
from ._frames import FRAME_ALPHA_SPEC as FRAME_ALPHA_SPEC
from ._frames import FRAME_NOISE_SIGMA as FRAME_NOISE_SIGMA
from ._frames import FRAME_PRIOR_KIND as FRAME_PRIOR_KIND
from ._frames import FrameOperator as FrameOperator
from ._frames import FrameStack as FrameStack
from ._frames import capture_frames as capture_frames
from ._frames import frame_intensity as frame_intensity
from ._frames import frame_times_us as frame_times_us
from ._frames import matched_frame_count as matched_frame_count
from ._frames import reconstruct_frames as reconstruct_frames
from ._gaptv import gap_tv as gap_tv
from ._gaptv import tv_denoise as tv_denoise
from ._nnls import nonneg_lsq_shared as nonneg_lsq_shared
