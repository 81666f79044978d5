"""Check a design with the exact pipeline: simulate → reconstruct → metrics, rates."""

from __future__ import annotations

import time

import jax.random as jr
import numpy as np

from .._base import evaluate
from .._model import Rig, Scene, load_scene
from .._reconstruct import reconstruct
from .._simulate import simulate
from ._objective import DEFAULT_GAINS
from ._space import DesignLimits, DesignParams

__all__ = ["evaluate_design", "training_scene"]


def training_scene(
    scene: str = "tcs",
    gains=DEFAULT_GAINS,
    repeats: int = 1,
    *,
    limit: int | None = None,
) -> Scene:
    """The design problem's training reflectances as a scene for the exact simulator:
    one column per (gain, spectrum), `repeats` rows; `limit` picks the same spectra as
    :func:`training_spectra`."""
    sc = load_scene(scene)
    pal0 = sc.palette
    if limit is not None:
        pick = np.unique(np.linspace(0, pal0.shape[0] - 1, limit).round().astype(int))
        pal0 = pal0[pick]
    pal = np.concatenate([float(g) * pal0 for g in gains])
    labels = np.tile(np.arange(pal.shape[0]), (repeats, 1))
    return Scene(pal, sc.wavelengths_nm, labels)


def evaluate_design(
    params: DesignParams,
    scene: Scene | str = "colorchecker",
    *,
    base_rig: Rig | None = None,
    limits: DesignLimits | None = None,
    size: tuple[int, int] | None = (24, 36),
    sweeps: int = 1,
    seed: int = 0,
    threshold_spread: float = 0.0,
    **reconstruct_kw,
) -> dict:
    """Simulate `scene` with the exact simulator under the design and reconstruct it.

    **Arguments:**

    - `params`: the design; `base_rig`: everything else (default: the paper rig
      without threshold mismatch).
    - `scene`: a :class:`Scene` or a built-in name (at `size`).
    - `limits`: for the event-rate scaling and the constraint report.
    - `sweeps`, `seed`: simulation; further keywords go to `reconstruct`.
    - `threshold_spread`: per-pixel threshold mismatch relative to C (0.067 is the
      paper's C ~ N(0.15, 0.01)); the drawn maps are given to the reconstruction
      (a calibrated sensor), as the design loss assumes.

    **Returns:** a dict with `sam_deg`, `psnr_db`, `rms`, `ssim`, `events_per_pixel`
    (per sweep), `event_rate_ev_s` (scaled to the full sensor at the design's sweep
    rate), `max_sweep_rate_hz` (the most the sensor and the motor allow),
    `feasible` (every hardware limit met), `constraints` and `seconds`. Raises
    `ValueError` for a design whose sweep does not fit its period.
    """
    limits = limits or DesignLimits()
    base_rig = base_rig or Rig(threshold_sigma=0.0)
    if isinstance(scene, str):
        scene = load_scene(scene, size)
    if threshold_spread < 0:
        raise ValueError("threshold_spread must be >= 0")
    rig = params.to_rig(base_rig)
    if threshold_spread > 0:
        rig = rig.replace_host(
            threshold_sigma=threshold_spread * float(params.threshold)
        )
    t0 = time.perf_counter()
    events, info = simulate(
        scene, rig, sweeps=sweeps, key=jr.key(seed), return_info=True
    )
    if threshold_spread > 0:
        reconstruct_kw.setdefault("threshold_on_map", info.threshold_on)
        reconstruct_kw.setdefault("threshold_off_map", info.threshold_off)
    cube = reconstruct(events, rig, **reconstruct_kw)
    seconds = time.perf_counter() - t0
    metrics = evaluate(cube, scene.truth_cube(rig.grid))
    n_px = scene.height * scene.width
    per_px = len(events) / n_px / sweeps
    f = float(params.sweep_rate_hz)
    rate = per_px * limits.sensor_pixels * f
    c = float(params.baseline_rel)
    g = rig.grid
    swept = (1.0 - limits.column_spread) * np.pi * float(params.beta_nm_per_rad)
    fwhm, start = float(params.fwhm_nm), float(params.sweep_start_nm)
    cons = {
        "event_rate": float(np.log(max(rate, 1e-30) / limits.max_event_rate_ev_s)),
        "rotation": float(np.log(f / limits.max_sweep_rate_hz)),
        "light": float(np.log(limits.min_baseline_rel / c)),
        "sweep_start": (start + 2 * fwhm - g.start_nm) / 10.0,
        "sweep_end": (g.stop_nm + 2 * fwhm - start - swept) / 10.0,
    }
    sensor_max = limits.max_event_rate_ev_s / max(per_px * limits.sensor_pixels, 1e-30)
    return {
        **{k: float(v) for k, v in metrics.items()},
        "events_per_pixel": per_px,
        "event_rate_ev_s": rate,
        "max_sweep_rate_hz": min(sensor_max, limits.max_sweep_rate_hz),
        "feasible": bool(all(v <= 1e-9 for v in cons.values())),
        "constraints": cons,
        "seconds": seconds,
    }
