"""Frame-based and CASSI baselines for comparison.

Public namespace `evhsi_jax.baselines`; the implementation lives in private modules."""

from ._baselines import CassiOperator as CassiOperator
from ._baselines import FrameOperator as FrameOperator
from ._baselines import FrameStack as FrameStack
from ._baselines import PatchConfig as PatchConfig
from ._baselines import SpectralBasis as SpectralBasis
from ._baselines import basis_project as basis_project
from ._baselines import capture_frames as capture_frames
from ._baselines import cassi_measure as cassi_measure
from ._baselines import desci as desci
from ._baselines import gap_tv as gap_tv
from ._baselines import learn_basis as learn_basis
from ._baselines import matched_frame_count as matched_frame_count
from ._baselines import random_mask as random_mask
from ._baselines import reconstruct_frames as reconstruct_frames
from ._baselines import reflectance_basis as reflectance_basis
from ._baselines import training_reflectances as training_reflectances

__all__ = [
    "CassiOperator",
    "FrameOperator",
    "FrameStack",
    "PatchConfig",
    "SpectralBasis",
    "basis_project",
    "capture_frames",
    "cassi_measure",
    "desci",
    "gap_tv",
    "learn_basis",
    "matched_frame_count",
    "random_mask",
    "reconstruct_frames",
    "reflectance_basis",
    "training_reflectances",
]
