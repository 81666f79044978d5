"""Design parameters, their search box, and the hardware limits of the rig.

A design is six scalars in physical units (:class:`DesignParams`): the band FWHM, the
sweep coefficient β, the band start λ0, the constant light c, the contrast threshold C
(ON = OFF) and the sweep rate. The channel grid, the refractory time and the spectra
D(λ), E(λ) stay those of the base rig.

**Box.** :class:`DesignSpace` maps each parameter to an unconstrained number through a
sigmoid box, $p = lo + (hi - lo)\\,\\mathrm{sigmoid}(u)$ — on a log scale for the ratio
quantities c, C and the sweep rate — so every optimiser step stays inside the box. The
lower sweep-rate bound is the application's frame-rate requirement (the event budget
shrinks as the rate grows, so an optimum sits on it).

**Hardware limits** (:class:`DesignLimits`, each a normalised constraint $g \\le 0$):

- sensor event rate: events per sweep × sweeps/s ≤ 80 Mev/s (IMX636), as
  $\\log(R/R_{max})$;
- mechanical rotation: sweep rate ≤ 30 sweeps/s, as $\\log(f/f_{max})$;
- minimum light: c ≥ `min_baseline_rel`, as $\\log(c_{min}/c)$ — the darkest level any
  pixel sees is c; below ~1 % of a white pixel's peak a DVS pixel's latency and noise
  grow (an assumption to adjust to the sensor at hand);
- sweep geometry (`_simulate._check_sweep_fits`): for every column the band must start
  below the channels, $λ_0 \\le λ_{start} - 2\\,\\mathrm{FWHM}$, and pass beyond them
  within the period, $λ_0 + (1 - s)πβ \\ge λ_{stop} + 2\\,\\mathrm{FWHM}$ with $s$ = 0.15
  the default column stagger (in one period $P$ the pattern turns by $ωP = π$ rad);
  in units of 10 nm.

They enter the design loss as $ρ \\sum \\max(0, g + m)^2$ with a small margin $m$.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._model import COLUMN_SPREAD, Rig

__all__ = ["DesignParams", "DesignSpace", "DesignLimits", "constraint_values"]

PARAM_NAMES = (
    "fwhm_nm",
    "beta_nm_per_rad",
    "sweep_start_nm",
    "baseline_rel",
    "threshold",
    "sweep_rate_hz",
)
_LOG_SCALE = {"baseline_rel", "threshold", "sweep_rate_hz"}


def _scalar(v):
    return jnp.asarray(v, dtype=float)


class DesignParams(eqx.Module):
    """One design, six scalars in physical units (a pytree: differentiate through it).

    - `fwhm_nm`: FWHM of the swept band, nm.
    - `beta_nm_per_rad`: sweep coefficient β, nm per radian of pattern rotation.
    - `sweep_start_nm`: band centre λ0 at the sweep start, nm.
    - `baseline_rel`: constant light c, fraction of a white pixel's peak intensity.
    - `threshold`: contrast threshold C (ON and OFF), log units.
    - `sweep_rate_hz`: sweeps per second.
    """

    fwhm_nm: Float[Array, ""] = eqx.field(converter=_scalar)
    beta_nm_per_rad: Float[Array, ""] = eqx.field(converter=_scalar)
    sweep_start_nm: Float[Array, ""] = eqx.field(converter=_scalar)
    baseline_rel: Float[Array, ""] = eqx.field(converter=_scalar)
    threshold: Float[Array, ""] = eqx.field(converter=_scalar)
    sweep_rate_hz: Float[Array, ""] = eqx.field(converter=_scalar)

    @classmethod
    def from_rig(cls, rig: Rig) -> DesignParams:
        """The design of a rig (C is the mean of its ON and OFF thresholds)."""
        return cls(
            rig.fwhm_nm,
            rig.beta_nm_per_rad,
            rig.sweep_start_nm,
            rig.baseline_rel,
            0.5 * (rig.threshold_on + rig.threshold_off),
            rig.sweep_rate_hz,
        )

    def to_rig(self, base: Rig) -> Rig:
        """`base` with this design's leaves (differentiable; `base` keeps its dtype)."""
        dtype = base.fwhm_nm.dtype
        vals = tuple(jnp.asarray(getattr(self, k), dtype) for k in PARAM_NAMES)
        fwhm, beta, start, c, thr, rate = vals
        return base.with_leaves(
            fwhm_nm=fwhm,
            beta_nm_per_rad=beta,
            sweep_start_nm=start,
            baseline_rel=c,
            threshold_on=thr,
            threshold_off=thr,
            sweep_rate_hz=rate,
        )

    def as_dict(self) -> dict[str, float]:
        """Plain floats, for printing and JSON."""
        return {k: float(getattr(self, k)) for k in PARAM_NAMES}

    @classmethod
    def from_dict(cls, d: dict) -> DesignParams:
        missing = set(PARAM_NAMES) - set(d)
        if missing:
            raise ValueError(f"design lacks {sorted(missing)}")
        return cls(*(d[k] for k in PARAM_NAMES))


@dataclasses.dataclass(frozen=True)
class DesignSpace:
    """The search box, `(lo, hi)` per parameter in physical units (static, hashable).

    The FWHM is capped at 50 nm (the band table's traced range). The default
    sweep-rate box starts at 2 sweeps/s; set its lower end to the frame rate the
    application needs.
    """

    fwhm_nm: tuple[float, float] = (5.0, 40.0)
    beta_nm_per_rad: tuple[float, float] = (135.0, 400.0)
    sweep_start_nm: tuple[float, float] = (250.0, 395.0)
    baseline_rel: tuple[float, float] = (0.003, 0.3)
    threshold: tuple[float, float] = (0.06, 0.6)
    sweep_rate_hz: tuple[float, float] = (2.0, 60.0)

    def __post_init__(self):
        for k in PARAM_NAMES:
            lo, hi = getattr(self, k)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"design box for {k} must be finite with lo < hi")
            if k in _LOG_SCALE and lo <= 0:
                raise ValueError(f"design box for {k} must be > 0")
        if self.fwhm_nm[1] > 50.0 or self.fwhm_nm[0] <= 0:
            raise ValueError("the FWHM box must lie in (0, 50] nm")

    def _scale(self, k):
        lo, hi = getattr(self, k)
        return (math.log(lo), math.log(hi)) if k in _LOG_SCALE else (lo, hi)

    def from_unconstrained(self, u: DesignParams) -> DesignParams:
        """Physical design from unconstrained values (inside the box by construction)."""
        out = []
        for k in PARAM_NAMES:
            lo, hi = self._scale(k)
            v = lo + (hi - lo) * jax.nn.sigmoid(getattr(u, k))
            out.append(jnp.exp(v) if k in _LOG_SCALE else v)
        return DesignParams(*out)

    def to_unconstrained(self, p: DesignParams) -> DesignParams:
        """Inverse of :meth:`from_unconstrained`; values are clipped just inside."""
        out = []
        for k in PARAM_NAMES:
            lo, hi = self._scale(k)
            v = getattr(p, k)
            v = jnp.log(v) if k in _LOG_SCALE else v
            s = jnp.clip((v - lo) / (hi - lo), 1e-6, 1.0 - 1e-6)
            out.append(jnp.log(s) - jnp.log1p(-s))
        return DesignParams(*out)

    def contains(self, p: DesignParams) -> bool:
        return all(
            getattr(self, k)[0] <= float(getattr(p, k)) <= getattr(self, k)[1]
            for k in PARAM_NAMES
        )


@dataclasses.dataclass(frozen=True)
class DesignLimits:
    """What the hardware allows (static). See the module docstring.

    - `max_event_rate_ev_s`: sensor read-out limit (IMX636: 80 Mev/s).
    - `sensor_pixels`: pixels the event rate is scaled to (1280 × 720).
    - `max_sweep_rate_hz`: mechanical limit (1800 rpm: 30 sweeps/s).
    - `min_baseline_rel`: least constant light c.
    - `column_spread`: column stagger as a fraction of the period (rig default 0.15).
    - `penalty_weight`: ρ of the quadratic penalty; `margin`: m, in the constraints'
      units (0.01 ≈ 1 % on the log-ratio limits, 0.1 nm on the geometry).
    """

    max_event_rate_ev_s: float = 80e6
    sensor_pixels: int = 1280 * 720
    max_sweep_rate_hz: float = 30.0
    min_baseline_rel: float = 0.01
    column_spread: float = COLUMN_SPREAD
    penalty_weight: float = 1e3
    margin: float = 0.01


def event_rate_ev_s(
    events_per_pixel: Float[Array, ""], sweep_rate_hz, limits: DesignLimits
):
    """Sensor event rate: mean events per pixel and sweep × pixels × sweeps/s."""
    return events_per_pixel * limits.sensor_pixels * sweep_rate_hz


def constraint_values(
    params: DesignParams,
    events_per_pixel: Float[Array, ""],
    rig: Rig,
    limits: DesignLimits,
) -> dict[str, Float[Array, ""]]:
    """Normalised hardware constraints, feasible where ≤ 0 (differentiable).

    **Arguments:** the design, the expected events per pixel and sweep (e.g. from the
    soft event model), the rig (for the channel range), the limits.

    **Returns:** `{"event_rate", "rotation", "light", "sweep_start", "sweep_end"}`.
    """
    g = rig.grid
    rate = event_rate_ev_s(events_per_pixel, params.sweep_rate_hz, limits)
    swept = (1.0 - limits.column_spread) * jnp.pi * params.beta_nm_per_rad
    return {
        "event_rate": jnp.log(jnp.maximum(rate, 1e-30) / limits.max_event_rate_ev_s),
        "rotation": jnp.log(params.sweep_rate_hz / limits.max_sweep_rate_hz),
        "light": jnp.log(limits.min_baseline_rel / params.baseline_rel),
        "sweep_start": (params.sweep_start_nm + 2.0 * params.fwhm_nm - g.start_nm)
        / 10.0,
        "sweep_end": (g.stop_nm + 2.0 * params.fwhm_nm - params.sweep_start_nm - swept)
        / 10.0,
    }


def penalty(cons: dict, limits: DesignLimits) -> Float[Array, ""]:
    """$ρ \\sum_i \\max(0, g_i + m)^2$."""
    total = 0.0
    for v in cons.values():
        total = total + jnp.square(jax.nn.relu(v + limits.margin))
    return limits.penalty_weight * total
