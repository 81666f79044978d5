"""Per-pixel box-QP reconstruction of spectra from events."""

from ._pipeline import (
    SOLVERS as SOLVERS,
    ReconstructionInfo as ReconstructionInfo,
    SolverSpec as SolverSpec,
    reconstruct as reconstruct,
    solver_spec as solver_spec,
)
from ._problem import (
    ProblemConfig as ProblemConfig,
    pixel_system as pixel_system,
    spectral_prior_matrix as spectral_prior_matrix,
)
from ._solvers import (
    apg as apg,
    kkt_residual as kkt_residual,
    projected_newton as projected_newton,
    svd_nullvector as svd_nullvector,
)
