"""Helpers shared by the baseline studies (bandwidth, event_rate, cassi_compare).

`bl` is the namespace that holds the baseline functions: the top-level package once
they are re-exported there, else the `evhsi_jax._baselines` sub-package.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import evhsi_jax as ev

if hasattr(ev, "capture_frames"):
    bl = ev
else:  # until the public re-export lands
    from evhsi_jax import _baselines as bl

RESULTS = Path(__file__).resolve().parent / "results"

__all__ = ["bl", "RESULTS", "machine", "write_json", "table", "Timer", "metrics"]


def machine() -> dict:
    """What the numbers were measured on."""
    import jax

    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
    }


def write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=_jsonable) + "\n")


def _jsonable(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def metrics(est, truth) -> dict:
    """SAM, PSNR, SSIM, RMS of a cube against the truth, rounded for tables."""
    est = np.asarray(est)
    return {k: round(float(v), 4) for k, v in ev.evaluate(est, truth).items()}


def table(rows: list[dict], cols: list[str], title: str = "") -> str:
    """A plain-text table (also valid Markdown)."""

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}" if abs(v) < 1e5 else f"{v:.3e}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]

    def line(xs):
        return "| " + " | ".join(x.ljust(w) for x, w in zip(xs, widths)) + " |"

    out = [title] if title else []
    out += [line(cols), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    out += [line(x) for x in cells]
    return "\n".join(out)


class Timer:
    """Wall time of a block: `with Timer() as t: ...; t.seconds`."""

    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0
