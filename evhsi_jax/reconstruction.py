"""The per-pixel box-QP reconstruction and its parts.

Public namespace `evhsi_jax.reconstruction`; the implementation lives in private modules."""

from ._reconstruct import DEFAULT_WIENER_REG as DEFAULT_WIENER_REG
from ._reconstruct import SOLVERS as SOLVERS
from ._reconstruct import ProblemConfig as ProblemConfig
from ._reconstruct import ReconstructionInfo as ReconstructionInfo
from ._reconstruct import SolverSpec as SolverSpec
from ._reconstruct import batch_sizes as batch_sizes
from ._reconstruct import deblur_cube as deblur_cube
from ._reconstruct import kkt_residual as kkt_residual
from ._reconstruct import pixel_system as pixel_system
from ._reconstruct import reconstruct as reconstruct
from ._reconstruct import solver_spec as solver_spec
from ._reconstruct import spectral_prior_matrix as spectral_prior_matrix
from ._reconstruct import warp_times as warp_times

__all__ = [
    "reconstruct",
    "ProblemConfig",
    "SolverSpec",
    "SOLVERS",
    "solver_spec",
    "ReconstructionInfo",
    "pixel_system",
    "spectral_prior_matrix",
    "kkt_residual",
    "deblur_cube",
    "DEFAULT_WIENER_REG",
    "batch_sizes",
    "warp_times",
]
