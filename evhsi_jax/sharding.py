"""Scale-out over devices and hosts.

Public namespace `evhsi_jax.sharding`; the implementation lives in private modules."""

from ._shard import initialize_distributed as initialize_distributed
from ._shard import is_main_process as is_main_process
from ._shard import pixel_mesh as pixel_mesh

__all__ = ["pixel_mesh", "initialize_distributed", "is_main_process"]
