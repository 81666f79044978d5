"""Optical design by gradients.

Public namespace `evhsi_jax.design`; the implementation lives in private modules."""

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

__all__ = [
    "DesignLimits",
    "DesignParams",
    "DesignProblem",
    "DesignResult",
    "DesignSpace",
    "constraint_values",
    "design_loss",
    "design_problem",
    "design_value_and_grad",
    "evaluate_design",
    "optimise_design",
    "save_trajectory",
    "training_scene",
    "training_spectra",
]
