"""Scale-out over devices and hosts.

Public namespace `evhsi_jax.sharding`; the implementation lives in private modules."""

from ._base import initialize_distributed as initialize_distributed
from ._base import is_main_process as is_main_process
from ._base import pixel_mesh as pixel_mesh

__all__ = ["pixel_mesh", "initialize_distributed", "is_main_process"]
