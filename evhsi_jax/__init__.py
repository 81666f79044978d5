"""evhsi_jax: event-based active hyperspectral imaging in JAX."""

from ._events import EventStream as EventStream

__version__ = "0.1.0"
