"""Gradient-based optical design: a differentiable design loss and its optimiser."""

from ._evaluate import evaluate_design as evaluate_design
from ._evaluate import training_scene as training_scene
from ._gradient import design_value_and_grad as design_value_and_grad
from ._objective import DesignProblem as DesignProblem
from ._objective import design_loss as design_loss
from ._objective import design_problem as design_problem
from ._objective import training_spectra as training_spectra
from ._optimise import DesignResult as DesignResult
from ._optimise import optimise_design as optimise_design
from ._optimise import save_trajectory as save_trajectory
from ._space import DesignLimits as DesignLimits
from ._space import DesignParams as DesignParams
from ._space import DesignSpace as DesignSpace
from ._space import constraint_values as constraint_values
