"""Stage 2, the simulator: scenes and a rig to event streams, with the sensor effects
of README "Sensor model"."""

from ._capture import SimulationInfo as SimulationInfo
from ._capture import simulate as simulate
from ._capture import threshold_maps as threshold_maps
