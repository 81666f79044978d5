"""Accuracy metrics.

Public namespace `evhsi_jax.metrics`; the implementation lives in private modules."""

from ._base import evaluate as evaluate
from ._base import per_label_table as per_label_table
from ._base import psnr_db as psnr_db
from ._base import rms as rms
from ._base import sam_deg as sam_deg
from ._base import sam_map_deg as sam_map_deg
from ._base import ssim as ssim

__all__ = [
    "evaluate",
    "sam_deg",
    "sam_map_deg",
    "psnr_db",
    "rms",
    "ssim",
    "per_label_table",
]
