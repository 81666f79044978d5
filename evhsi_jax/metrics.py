"""Accuracy metrics.

Public namespace `evhsi_jax.metrics`; the implementation lives in private modules."""

from ._metrics import evaluate as evaluate
from ._metrics import per_label_table as per_label_table
from ._metrics import psnr_db as psnr_db
from ._metrics import rms as rms
from ._metrics import sam_deg as sam_deg
from ._metrics import sam_map_deg as sam_map_deg
from ._metrics import ssim as ssim

__all__ = [
    "evaluate",
    "sam_deg",
    "sam_map_deg",
    "psnr_db",
    "rms",
    "ssim",
    "per_label_table",
]
