"""The rig: every physical parameter of the capture system, as one parameter pytree.

A :class:`Rig` is an `eqx.Module`. Its array fields are the differentiable leaves that
calibration and design studies fit (band FWHM, sweep coefficient β, band start λ0, sweep
rate, column offsets τx, ON/OFF thresholds, refractory time, constant light c, the camera
response D(λ) and lamp E(λ) on the fine grid). Only what shapes the computation is
static: sizes, the spectral grid, the reset mode, the band's sampled profile, whether
the photoreceptor low-pass is on. Host-side settings (the simulation's seed, threshold
spread and background rate, the sensor's noise magnitudes, the post-solve channel
gain) are dynamic leaves held as NumPy values, so a kernel that takes the rig is
compiled once whatever they are (`tests/forward/test_rig.py` counts traces with
`eqx.debug.assert_max_traces`). A per-pixel threshold map is not part of a rig: the
file pair of a calibration names it, and :func:`evhsi_jax.load_calibration` reads
both. JSON I/O follows the contract of DESIGN.md: every key is optional and takes
the default rig's value when left out.

Timing model (documented choice, see README "Physics"): one sweep per mirror revolution,
sweep period $P = 1/f$ with $f$ = `sweep_rate_hz`; the illumination pattern turns at
$ω = π f$ rad/s (half the mirror speed, paper Eq. 1); column `x` sees the band centred at
$λ_c(t) = λ_0 + β ω ((t \\bmod P) + τ_x)$. With the defaults (β = 185 nm/rad, λ0 = 360 nm)
the band crosses 360→796 nm (the channels ± 2 FWHM) in 0.75 P, and the default offsets
$τ_x = -0.15 P · x/(W-1)$ stagger the columns over another 0.15 P, leaving 0.1 P of dark
time before the next sweep. At 30 sweeps/s a 17.5 nm band then takes about 1 ms to cross
a pixel; consecutive events of a pixel are then ≥ ~130 µs apart on the ColorChecker, so
the 50 µs refractory period rarely binds (it does at faster sweeps or lower thresholds,
and the reconstruction models it either way).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import types
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._base import (
    SpectralGrid,
    atomic_write,
    default_camera_response,
    default_lamp_spectrum,
    resample,
)

__all__ = [
    "Rig",
    "DEFAULTS",
    "SENSOR_PRESETS",
    "SensorEffects",
    "default_column_offsets_us",
    "skewed_band_profile",
]

#: The paper's simulated rig (supplement 6.4), in the JSON contract's keys and units.
DEFAULTS: dict[str, Any] = {
    "channels": 72,
    "channel_start_nm": 400.0,
    "channel_stop_nm": 760.0,
    "fine_step_nm": 1.0,
    "fwhm_nm": 17.5,
    "samples_per_sweep": 1200,
    "sweep_rate_hz": 30.0,
    "beta_nm_per_rad": 185.0,
    "sweep_start_nm": 360.0,
    "column_offsets_us": None,
    "threshold_on": 0.15,
    "threshold_off": 0.15,
    "threshold_sigma": 0.01,
    "refractory_us": 50.0,
    "baseline_rel": 0.03,
    "log_eps": 1e-5,
    "noise_rate_hz": 0.0,
    "threshold_noise": 0.0,
    "on_off_correlation": 1.0,
    "timestamp_jitter_us": 0.0,
    "latency_us": 0.0,
    "photoreceptor_hz": 0.0,
    "hot_pixel_fraction": 0.0,
    "hot_pixel_rate_hz": 1000.0,
    "sweep_rate_jitter": 0.0,
    "psf_sigma_px": 0.0,
    "sweep_curvature_nm": 0.0,
    "band_profile": None,
    "reset_mode": "release",
    "seed": 0,
    "camera_response": None,
    "lamp": None,
    "threshold_map": None,
    "channel_gain": None,
}

_DOC = {
    "channels": "number of spectral channels M",
    "channel_start_nm": "lower edge of the first channel, nm",
    "channel_stop_nm": "upper edge of the last channel, nm",
    "fine_step_nm": "simulator's spectral sub-bin width, nm",
    "fwhm_nm": "FWHM of the swept narrow band, nm",
    "samples_per_sweep": "time samples per sweep period",
    "sweep_rate_hz": "sweeps per second (mirror revolutions per second)",
    "beta_nm_per_rad": "sweep coefficient β, nm per radian of pattern rotation",
    "sweep_start_nm": "band centre λ0 at t + τx = 0, nm",
    "column_offsets_us": "τx per column, µs (null: default linear stagger)",
    "threshold_on": "ON contrast threshold, log units",
    "threshold_off": "OFF contrast threshold, log units",
    "threshold_sigma": "per-pixel threshold spread (simulation only), log units",
    "refractory_us": "refractory period, µs",
    "baseline_rel": "constant light c, fraction of a white pixel's peak intensity",
    "log_eps": "ε in log(I + ε), fraction of a white pixel's peak intensity",
    "noise_rate_hz": "background-activity (noise) events per pixel per second",
    "threshold_noise": "per-crossing threshold noise σ, log units (each crossing draws "
    "its own threshold around the pixel's)",
    "on_off_correlation": "correlation of a pixel's ON and OFF threshold deviations "
    "(1: one shared deviation; 0: independent; simulation only)",
    "timestamp_jitter_us": "Gaussian timestamp jitter σ, µs",
    "latency_us": "constant event latency, µs (simulation only; absorbed by τx)",
    "photoreceptor_hz": "photoreceptor low-pass cut-off at a white pixel's peak "
    "intensity, Hz, proportional to intensity (0: instantaneous)",
    "hot_pixel_fraction": "fraction of hot pixels firing steadily (simulation only)",
    "hot_pixel_rate_hz": "event rate of a hot pixel, Hz (simulation only)",
    "sweep_rate_jitter": "relative σ of each sweep's mirror speed (simulated; "
    "calibrate measures it from the chart's sweeps, reconstruct each recording's)",
    "psf_sigma_px": "Gaussian optical point-spread σ, pixels (simulation only)",
    "sweep_curvature_nm": "band-centre deviation from the linear sweep at mid-range, "
    "nm (parabolic, zero at the channel range's ends)",
    "band_profile": "null (Gaussian of fwhm_nm) or {offset_nm: [...], values: [...]}: "
    "the band's sampled spectral profile around its centre",
    "reset_mode": "reference after an event: 'release' (level at end of refractory, "
    "paper Eq. 2) or 'event' (previous reference ± C)",
    "seed": "default PRNG seed for simulation",
    "camera_response": "D(λ): null or {wavelengths_nm: [...], values: [...]}",
    "lamp": "E(λ): null or {wavelengths_nm: [...], values: [...]}",
    "threshold_map": "null or a sibling .npz with per-pixel threshold_on/threshold_off "
    "(H, W), log units (written by `evhsi calibrate`)",
    "channel_gain": "null or M per-channel response factors from a white reference; "
    "reconstructed spectra are divided by them",
}

#: Rig keys that describe the event sensor's non-idealities (all 0 / off by default:
#: today's ideal sensor). The simulator draws them; `evhsi calibrate` measures those it
#: can (threshold_noise, timestamp_jitter_us, noise_rate_hz) and the reconstruction
#: weights its rows with them.
EFFECT_KEYS = (
    "threshold_noise",
    "on_off_correlation",
    "timestamp_jitter_us",
    "latency_us",
    "photoreceptor_hz",
    "hot_pixel_fraction",
    "hot_pixel_rate_hz",
    "sweep_rate_jitter",
    "psf_sigma_px",
)

#: Host-side rig fields besides the sensor effects (:meth:`Rig.replace_host`).
HOST_FIELDS = ("threshold_sigma", "noise_rate_hz", "seed", "channel_gain")


class SensorEffects(eqx.Module):
    """The event sensor's non-idealities.

    Defaults are the ideal sensor. Magnitudes of the `realistic` preset and where they
    come from: README "Sensor model". Fields are the rig keys of the same name. The
    magnitudes are dynamic leaves (0-d float64 NumPy arrays; read them with `float`);
    `photoreceptor_hz` is static because switching the low-pass on changes the model's
    equations (its value enters as a number).
    """

    threshold_noise: np.ndarray
    on_off_correlation: np.ndarray
    timestamp_jitter_us: np.ndarray
    latency_us: np.ndarray
    hot_pixel_fraction: np.ndarray
    hot_pixel_rate_hz: np.ndarray
    sweep_rate_jitter: np.ndarray
    psf_sigma_px: np.ndarray
    photoreceptor_hz: float = eqx.field(static=True)

    def __init__(self, **values):
        unknown = set(values) - set(EFFECT_KEYS)
        if unknown:
            raise TypeError(f"unknown sensor effects {sorted(unknown)}")
        for k in EFFECT_KEYS:
            v = float(values.get(k, DEFAULTS[k]))
            setattr(
                self, k, v if k == "photoreceptor_hz" else np.asarray(v, np.float64)
            )

    def as_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in EFFECT_KEYS}

    def floats(self) -> types.SimpleNamespace:
        """The values as Python floats, by attribute (for host code)."""
        return types.SimpleNamespace(**self.as_dict())


def skewed_band_profile(fwhm_nm: float, skew: float, n: int = 161) -> dict:
    """A skew-normal band profile with the given FWHM (peak 1), as the rig's
    `band_profile` JSON object. `skew` is the skew-normal shape α (0: Gaussian)."""
    from scipy.stats import skewnorm

    x = np.linspace(-6.0, 6.0, 4001)
    y = skewnorm.pdf(x, skew)
    y = y / y.max()
    above = x[y >= 0.5]
    width = above[-1] - above[0]
    mode = x[np.argmax(y)]
    off = np.linspace(-3.0 * fwhm_nm, 3.0 * fwhm_nm, n)
    vals = np.interp(off / fwhm_nm * width + mode, x, y)
    return {"offset_nm": off.tolist(), "values": (vals / vals.max()).tolist()}


#: Named sensor presets for the rig key `"sensor"` (explicit keys override them).
#: `realistic`: README "Sensor model" gives the sources of each magnitude.
SENSOR_PRESETS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "realistic": {
        "threshold_noise": 0.01,
        "on_off_correlation": 0.5,
        "timestamp_jitter_us": 5.0,
        "latency_us": 40.0,
        "photoreceptor_hz": 10000.0,
        "noise_rate_hz": 1.0,
        "hot_pixel_fraction": 0.001,
        "hot_pixel_rate_hz": 1000.0,
        "sweep_rate_jitter": 0.002,
        "psf_sigma_px": 0.5,
        "sweep_curvature_nm": 3.0,
        "band_profile": "skewed",
    },
}

COLUMN_SPREAD = (
    0.15  # fraction of the sweep period over which the columns are staggered
)
# Upper bounds of the size keys (far above any real rig; they stop typos early).
MAX_CHANNELS = 4096
MAX_SAMPLES_PER_SWEEP = 1 << 20
MAX_FINE_BINS = 200_000


def default_column_offsets_us(width: int, sweep_rate_hz: float) -> np.ndarray:
    """The default linear stagger $τ_x = -0.15 P · x/(W-1)$ in µs, shape `(W,)`."""
    if width < 1:
        raise ValueError(f"width must be >= 1, got {width}")
    period_us = 1e6 / sweep_rate_hz
    if width == 1:
        return np.zeros(1)
    return -COLUMN_SPREAD * period_us * np.arange(width) / (width - 1)


def _scalar(v) -> Float[Array, ""]:
    return jnp.asarray(v, dtype=float)


def _positive(name, v, *, allow_zero=False):
    try:
        if isinstance(v, (bool, str, bytes)):  # JSON true / "17.5" are not numbers
            raise TypeError
        v = float(v)
    except (TypeError, ValueError):
        raise ValueError(f"rig key {name!r} must be a number, got {v!r}") from None
    if not math.isfinite(v) or (v < 0 if allow_zero else v <= 0):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"rig key {name!r} must be finite and {bound}, got {v}")
    return v


def _spectrum_from_json(name, spec, grid: SpectralGrid, default_fn):
    fine = grid.fine_centres_nm
    if spec is None:
        return default_fn(fine), None
    if not isinstance(spec, dict) or set(spec) != {"wavelengths_nm", "values"}:
        raise ValueError(
            f"rig key {name!r} must be null or an object with 'wavelengths_nm' and "
            "'values' lists"
        )
    wl = np.asarray(spec["wavelengths_nm"], dtype=np.float64)
    vals = np.asarray(spec["values"], dtype=np.float64)
    if wl.shape != vals.shape or wl.ndim != 1:
        raise ValueError(
            f"rig key {name!r}: wavelengths_nm and values differ in length"
        )
    if np.any(vals < 0):
        raise ValueError(f"rig key {name!r}: values must be >= 0")
    out = resample(wl, vals, fine, name=f"rig key {name!r}")
    if out.max() <= 0:
        raise ValueError(f"rig key {name!r} is zero everywhere")
    return out / out.max(), {"wavelengths_nm": wl.tolist(), "values": vals.tolist()}


class Rig(eqx.Module):
    """Parameters of the whole capture system (the paper's simulated rig by default).

    Build with `Rig.from_dict({...})` / `Rig.load(path)` (validated, any key optional)
    or `Rig()` for the defaults; replace array leaves with :meth:`with_leaves`
    (differentiable), host-side settings with :meth:`replace_host` and static fields
    with :meth:`replace_static`.
    """

    fwhm_nm: Float[Array, ""]
    beta_nm_per_rad: Float[Array, ""]
    sweep_start_nm: Float[Array, ""]
    sweep_rate_hz: Float[Array, ""]
    threshold_on: Float[Array, ""]
    threshold_off: Float[Array, ""]
    refractory_us: Float[Array, ""]
    baseline_rel: Float[Array, ""]
    log_eps: Float[Array, ""]
    camera_response: Float[Array, " fine"]
    lamp: Float[Array, " fine"]
    column_offsets_us: Float[Array, " w"] | None
    sweep_curvature_nm: Float[Array, ""]
    # host-side settings: dynamic NumPy leaves (see the module docstring)
    threshold_sigma: np.ndarray
    noise_rate_hz: np.ndarray
    seed: np.ndarray
    channel_gain: np.ndarray
    effects: SensorEffects
    # the structure of the computation
    grid: SpectralGrid = eqx.field(static=True)
    samples_per_sweep: int = eqx.field(static=True)
    reset_mode: str = eqx.field(static=True)
    band_profile: tuple | None = eqx.field(static=True)
    #: The file's own spelling of D(λ) and E(λ) (JSON text, `null` for the defaults),
    #: kept to write them back as given; equal for rigs read from the same file.
    spectra_json: tuple = eqx.field(static=True)

    def __init__(self, **overrides):
        preset = overrides.pop("sensor", None)
        if preset is not None:  # as the JSON key: explicit keys override the preset
            if not isinstance(preset, str) or preset not in SENSOR_PRESETS:
                raise ValueError(
                    f"rig key 'sensor' must be one of {sorted(SENSOR_PRESETS)}, got "
                    f"{preset!r}"
                )
            overrides = {**SENSOR_PRESETS[preset], **overrides}
        unknown = sorted(set(overrides) - set(DEFAULTS))
        if unknown:  # a typo must not be silently ignored
            raise TypeError(
                f"unknown rig key(s) {unknown}; known keys: {sorted(DEFAULTS)}"
            )
        cfg = _validated({**DEFAULTS, **overrides})
        self.grid = SpectralGrid(
            cfg["channels"],
            cfg["channel_start_nm"],
            cfg["channel_stop_nm"],
            cfg["fine_step_nm"],
        )
        d, d_json = _spectrum_from_json(
            "camera_response",
            cfg["camera_response"],
            self.grid,
            default_camera_response,
        )
        e, e_json = _spectrum_from_json(
            "lamp", cfg["lamp"], self.grid, default_lamp_spectrum
        )
        self.spectra_json = (json.dumps(d_json), json.dumps(e_json))
        if cfg["threshold_map"] is not None:
            raise ValueError(
                "rig key 'threshold_map': a rig holds no per-pixel maps; read a "
                "calibration file pair with evhsi_jax.load_calibration(path)"
            )
        self.camera_response = jnp.asarray(d, dtype=float)
        self.lamp = jnp.asarray(e, dtype=float)
        for k in (
            "fwhm_nm",
            "beta_nm_per_rad",
            "sweep_start_nm",
            "sweep_rate_hz",
            "threshold_on",
            "threshold_off",
            "refractory_us",
            "baseline_rel",
            "log_eps",
            "sweep_curvature_nm",
        ):
            setattr(self, k, _scalar(cfg[k]))
        prof = cfg["band_profile"]
        self.band_profile = (
            None if prof is None else (tuple(prof["offset_nm"]), tuple(prof["values"]))
        )
        offs = cfg["column_offsets_us"]
        self.column_offsets_us = None if offs is None else jnp.asarray(offs, float)
        self.samples_per_sweep = cfg["samples_per_sweep"]
        for k, v in _host_leaves(cfg).items():
            setattr(self, k, v)
        self.reset_mode = cfg["reset_mode"]

    def with_leaves(self, **values) -> Rig:
        """A copy with array leaves replaced by name, e.g.
        `rig.with_leaves(fwhm_nm=x, threshold_on=c, threshold_off=c)`.

        Differentiable (`eqx.tree_at`): gradients flow into the new values, which is how
        the calibration and design code put traced parameters into a rig. Values keep
        their own dtype; unknown, static or host-side names raise (host settings:
        :meth:`replace_host`).
        """
        if not values:
            return self
        leaves = {
            f.name for f in dataclasses.fields(self) if not f.metadata.get("static")
        } - {*HOST_FIELDS, "effects"}
        bad = sorted(set(values) - leaves)
        if bad:
            raise AttributeError(f"not array leaves of Rig: {bad}")
        names = tuple(values)
        return eqx.tree_at(
            lambda r: tuple(getattr(r, k) for k in names),
            self,
            tuple(values[k] for k in names),
            is_leaf=lambda x: x is None,
        )

    def replace_static(self, **fields) -> Rig:
        """A copy with static fields replaced, unvalidated."""
        static = {f.name for f in dataclasses.fields(self) if f.metadata.get("static")}
        bad = sorted(set(fields) - static)
        if bad:
            raise AttributeError(
                f"not static fields of Rig: {bad} (array leaves: with_leaves; host "
                "settings: replace_host)"
            )
        return self._replaced(fields)

    def _replaced(self, fields: dict) -> Rig:
        import copy

        new = copy.copy(self)
        for k, v in fields.items():
            object.__setattr__(new, k, v)
        return new

    def with_band_profile(self, profile) -> Rig:
        """A copy with the rig key `band_profile` replaced (`None`, `"skewed"` or
        `{offset_nm, values}`), validated like a rig file's key."""
        prof = _band_profile(profile, {"fwhm_nm": float(self.fwhm_nm)})
        return self._replaced({
            "band_profile": None
            if prof is None
            else (tuple(prof["offset_nm"]), tuple(prof["values"]))
        })  # fmt: skip

    def replace_host(self, **values) -> Rig:
        """A copy with host-side settings replaced by their rig keys (`seed`,
        `threshold_sigma`, `noise_rate_hz`, `channel_gain` or a sensor-effect key such
        as `threshold_noise`), validated like a rig file's keys."""
        bad = sorted(set(values) - set(HOST_FIELDS) - set(EFFECT_KEYS))
        if bad:
            raise AttributeError(f"not host settings of Rig: {bad}")
        cfg = _validated(
            {**DEFAULTS, "channels": self.channels, **self._host_dict(), **values}
        )
        return self._replaced(_host_leaves(cfg))

    def _host_dict(self) -> dict:
        return {
            "threshold_sigma": float(self.threshold_sigma),
            "noise_rate_hz": float(self.noise_rate_hz),
            "seed": int(self.seed),
            "channel_gain": None
            if np.all(np.asarray(self.channel_gain) == 1.0)
            else [float(v) for v in np.asarray(self.channel_gain)],
            **self.effects.as_dict(),
        }

    def with_channels(self, channels: int) -> Rig:
        """The same rig recovering `channels` channels over the same range
        (`channel_start_nm`–`channel_stop_nm`): the band, sweep, sensor and column
        offsets kept, D(λ) and E(λ) put on the new fine grid from the file's
        spelling (or the defaults), a white reference's `channel_gain` linearly
        interpolated between the channel centres. The dtype is kept. The fine
        sub-bins are at most as wide as the rig's (each channel split into whole
        parts), so a chain of conversions can narrow them (72 → 48 → 72: 1 nm →
        0.94 nm → 0.83 nm; 72 ↔ 36 keeps 1 nm).

        The channel count sets the size of each pixel's QP: fewer channels are
        faster (the system's assembly and factorisation grow with the band's span
        in channels and with M) at the price of spectral detail narrower than a
        channel; README, "Fewer channels" measures both. A count the rig key
        `channels` refuses, or below 2, raises `ValueError` (the rig's validation)."""
        if channels == self.channels:
            return self
        cfg = {**self.to_dict(), "channels": channels}
        if cfg["channel_gain"] is not None:
            centres = SpectralGrid(channels, self.grid.start_nm, self.grid.stop_nm)
            cfg["channel_gain"] = np.interp(
                centres.centres_nm, self.grid.centres_nm, cfg["channel_gain"]
            ).tolist()
        return Rig.from_dict(cfg).astype(self.fwhm_nm.dtype)

    def astype(self, dtype) -> Rig:
        """The same rig with every floating-point physics leaf cast to `dtype` (for
        float64, call inside `jax.enable_x64(True)`); the host settings keep their
        float64 NumPy values (a measured noise level is not rounded to float32)."""
        cast = jax.tree.map(
            lambda a: jnp.asarray(a, dtype) if eqx.is_inexact_array(a) else a, self
        )
        return cast._replaced({k: getattr(self, k) for k in (*HOST_FIELDS, "effects")})

    # --- derived quantities ----------------------------------------------------------
    @property
    def channels(self) -> int:
        return self.grid.channels

    @property
    def wavelengths_nm(self) -> np.ndarray:
        """Channel centres, shape `(M,)`."""
        return self.grid.centres_nm

    @property
    def period_us(self) -> Float[Array, ""]:
        """Sweep period $P = 10^6 / f$ in µs."""
        return 1e6 / self.sweep_rate_hz

    @property
    def omega_rad_per_us(self) -> Float[Array, ""]:
        """Pattern angular speed $ω = π f$, in rad/µs."""
        return jnp.pi * self.sweep_rate_hz * 1e-6

    @property
    def band_speed_nm_per_us(self) -> Float[Array, ""]:
        """How fast the band centre moves across the spectrum, $βω$ in nm/µs (the
        linear part; `sweep_curvature_nm` bends it)."""
        return self.beta_nm_per_rad * self.omega_rad_per_us

    @property
    def baseline_level(self) -> Float[Array, ""]:
        """$c' = c + ε$: the relative intensity a pixel sees with the band off it
        (ambient baseline plus the log offset), the level every event chain starts
        from."""
        return self.baseline_rel + self.log_eps

    def column_offsets(self, width: int) -> Float[Array, " w"]:
        """τx for `width` columns in µs: the stored offsets or the default stagger."""
        if self.column_offsets_us is None:  # traceable in the sweep rate
            frac = jnp.asarray(
                default_column_offsets_us(width, 1e6), self.fwhm_nm.dtype
            )
            return frac * self.period_us
        if self.column_offsets_us.shape[0] != width:
            raise ValueError(
                f"rig has {self.column_offsets_us.shape[0]} column offsets but the "
                f"sensor is {width} columns wide"
            )
        return self.column_offsets_us

    def band_centre_nm(self, t_us, column_offset_us):
        """$λ_c = λ_0 + βω((t \\bmod P) + τ_x)$ for times `t_us` within/after a sweep."""
        local = jnp.mod(t_us, self.period_us)
        lin = self.sweep_start_nm + self.band_speed_nm_per_us * (
            local + column_offset_us
        )
        return lin + self.sweep_curvature_nm * self._curve(lin)

    def _curve(self, lin_nm):
        """Shape of the sweep's non-linearity: $1 - ((λ - λ_{mid})/h)^2$ over the
        channel range's midpoint and half-width (1 at mid-range, 0 at its ends)."""
        mid = 0.5 * (self.grid.start_nm + self.grid.stop_nm)
        half = 0.5 * (self.grid.stop_nm - self.grid.start_nm)
        return 1.0 - ((lin_nm - mid) / half) ** 2

    # --- JSON ------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Any) -> Rig:
        if not isinstance(data, dict):
            raise ValueError("a rig file must hold a JSON object")
        unknown = sorted(
            set(data) - set(DEFAULTS) - {"$schema", "comment", "sensor", "calibration"}
        )
        if unknown:
            raise ValueError(
                f"unknown rig key(s) {unknown}; known keys: {sorted(DEFAULTS)}"
            )
        # The constructor applies a `sensor` preset (explicit keys override it).
        data = {k: v for k, v in data.items() if k in DEFAULTS or k == "sensor"}
        return cls(**data)

    @classmethod
    def load(cls, path: str | os.PathLike, *, maps: str = "error") -> Rig:
        """Read a rig JSON file (keys left out take default values).

        A calibration file that names per-pixel threshold maps is refused (a bare rig
        would silently use the global thresholds): load it with
        :func:`evhsi_jax.load_calibration`, or pass `maps="ignore"` to read its rig
        alone (e.g. to simulate with a calibrated rig)."""
        return cls.load_file(path, maps=maps)[0]

    @classmethod
    def load_file(cls, path: str | os.PathLike, *, maps: str = "error"):
        """:meth:`load`, also returning the file's JSON object (for what a rig does
        not hold: the `calibration` report, the `threshold_map` name)."""
        if maps not in ("error", "ignore"):
            raise ValueError(f"maps must be 'error' or 'ignore', got {maps!r}")
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"rig file not found: {path}")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"{path} is not valid JSON ({err})") from None
        if isinstance(data, dict) and data.get("threshold_map") is not None:
            if maps == "error":
                raise ValueError(
                    f"{path} names per-pixel threshold maps "
                    f"({data['threshold_map']}) that a bare rig would ignore: load it "
                    "with evhsi_jax.load_calibration(path)"
                )
        rig_keys = {**data, "threshold_map": None} if isinstance(data, dict) else data
        try:
            return cls.from_dict(rig_keys), data
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None

    def to_dict(self, width: int | None = None) -> dict:
        """Every key resolved; `column_offsets_us` filled in for `width` if given."""
        g = self.grid
        out: dict[str, Any] = {
            "channels": g.channels,
            "channel_start_nm": g.start_nm,
            "channel_stop_nm": g.stop_nm,
            "fine_step_nm": g.fine_width_nm,
            "samples_per_sweep": self.samples_per_sweep,
        }
        for k in (
            "fwhm_nm",
            "sweep_rate_hz",
            "beta_nm_per_rad",
            "sweep_start_nm",
            "threshold_on",
            "threshold_off",
        ):
            out[k] = _json_floats(getattr(self, k))
        if width is not None:
            out["column_offsets_us"] = _json_floats(self.column_offsets(width))
        elif self.column_offsets_us is not None:
            out["column_offsets_us"] = _json_floats(self.column_offsets_us)
        else:
            out["column_offsets_us"] = None
        host = self._host_dict()
        out["threshold_sigma"] = host["threshold_sigma"]
        out["refractory_us"] = _json_floats(self.refractory_us)
        out["baseline_rel"] = _json_floats(self.baseline_rel)
        out["log_eps"] = _json_floats(self.log_eps)
        out["noise_rate_hz"] = host["noise_rate_hz"]
        for k in EFFECT_KEYS:
            out[k] = host[k]
        out["sweep_curvature_nm"] = _json_floats(self.sweep_curvature_nm)
        out["band_profile"] = (
            None
            if self.band_profile is None
            else {
                "offset_nm": list(self.band_profile[0]),
                "values": list(self.band_profile[1]),
            }
        )
        out["reset_mode"] = self.reset_mode
        out["seed"] = host["seed"]
        out["camera_response"] = json.loads(self.spectra_json[0])
        out["lamp"] = json.loads(self.spectra_json[1])
        out["threshold_map"] = None  # a rig alone has no maps (Calibration.save)
        out["channel_gain"] = host["channel_gain"]
        return out

    def save(self, path: str | os.PathLike, width: int | None = None) -> None:
        """Write the resolved rig as JSON, atomically."""
        text = json.dumps(self.to_dict(width), indent=2) + "\n"
        atomic_write(path, lambda f: f.write(text.encode()))

    @staticmethod
    def describe_keys() -> str:
        """One line per JSON key with its unit (for `--help`)."""
        return "\n".join(
            f"  {k:20s} {_DOC[k]} (default {DEFAULTS[k]})" for k in DEFAULTS
        )


def _json_floats(a):
    """Leaf values as JSON numbers, float32 ones by their shortest round-trip repr
    (0.15, not 0.15000000596046448); -0.0 becomes 0.0."""
    arr = np.asarray(a)
    if arr.dtype == np.float32:
        vals = [float(np.format_float_positional(v, unique=True)) for v in arr.ravel()]
    else:
        vals = [float(v) for v in arr.astype(np.float64).ravel()]
    vals = [v + 0.0 for v in vals]
    return vals[0] if arr.ndim == 0 else vals


def _band_profile(prof, cfg):
    if prof is None:
        return None
    if prof == "skewed":  # the realistic preset's band: skew-normal α = 3, same FWHM
        return skewed_band_profile(_positive("fwhm_nm", cfg["fwhm_nm"]), 3.0)
    msg = (
        "rig key 'band_profile' must be null, \"skewed\" or an object with "
        "'offset_nm' and 'values' lists of equal length (>= 3, offsets increasing, "
        "values >= 0, not all 0)"
    )
    if not isinstance(prof, dict) or set(prof) != {"offset_nm", "values"}:
        raise ValueError(msg)
    try:
        off = np.asarray(prof["offset_nm"], np.float64)
        val = np.asarray(prof["values"], np.float64)
    except (TypeError, ValueError):
        raise ValueError(msg) from None
    if (
        off.ndim != 1
        or off.shape != val.shape
        or off.size < 3
        or off.size > 100_000
        or not np.all(np.isfinite(off))
        or not np.all(np.isfinite(val))
        or np.any(np.diff(off) <= 0)
        or np.any(val < 0)
        or val.max() <= 0
    ):
        raise ValueError(msg)
    return {"offset_nm": off.tolist(), "values": (val / val.max()).tolist()}


def _host_leaves(cfg: dict) -> dict:
    """The host-side fields of a rig from validated keys: 0-d float64 (int64 seed) NumPy
    leaves; `channel_gain` always an array (ones: no correction), so the tree's
    structure is the same with and without a white-reference correction."""
    gain = cfg["channel_gain"]
    return {
        "threshold_sigma": np.asarray(float(cfg["threshold_sigma"]), np.float64),
        "noise_rate_hz": np.asarray(float(cfg["noise_rate_hz"]), np.float64),
        "seed": np.asarray(int(cfg["seed"]), np.int64),
        "channel_gain": np.asarray(
            np.ones(cfg["channels"]) if gain is None else gain, np.float64
        ),
        "effects": SensorEffects(**{k: cfg[k] for k in EFFECT_KEYS}),
    }


def _validated(cfg: dict) -> dict:
    out = dict(cfg)
    ch = cfg["channels"]
    if isinstance(ch, bool) or not isinstance(ch, (int, float)) or int(ch) != ch:
        raise ValueError(f"rig key 'channels' must be an integer, got {ch!r}")
    out["channels"] = int(ch)
    sps = cfg["samples_per_sweep"]
    if isinstance(sps, bool) or not isinstance(sps, (int, float)) or int(sps) != sps:
        raise ValueError(f"rig key 'samples_per_sweep' must be an integer, got {sps!r}")
    if int(sps) < 16:
        raise ValueError(f"rig key 'samples_per_sweep' must be >= 16, got {sps}")
    # Sizes are checked before anything is allocated: every array of a run grows
    # with them (a typo like 1e9 channels must not eat the machine's memory).
    if not 1 <= out["channels"] <= MAX_CHANNELS:
        raise ValueError(f"rig key 'channels' must be in [1, {MAX_CHANNELS}], got {ch}")
    if int(sps) > MAX_SAMPLES_PER_SWEEP:
        raise ValueError(
            f"rig key 'samples_per_sweep' must be <= {MAX_SAMPLES_PER_SWEEP}, got {sps}"
        )
    out["samples_per_sweep"] = int(sps)
    for k in (
        "fwhm_nm",
        "sweep_rate_hz",
        "beta_nm_per_rad",
        "threshold_on",
        "threshold_off",
        "log_eps",
        "fine_step_nm",
        "channel_start_nm",
        "channel_stop_nm",
    ):
        out[k] = _positive(k, cfg[k])
    out["refractory_us"] = _positive("refractory_us", cfg["refractory_us"])
    bins = (out["channel_stop_nm"] - out["channel_start_nm"]) / out["fine_step_nm"]
    if bins > MAX_FINE_BINS:
        raise ValueError(
            f"rig key 'fine_step_nm' {out['fine_step_nm']:g} makes {bins:.3g} "
            f"simulator bins over the channel range (at most {MAX_FINE_BINS})"
        )
    for k in ("threshold_sigma", "baseline_rel", "noise_rate_hz") + EFFECT_KEYS:
        out[k] = _positive(k, cfg[k], allow_zero=True)
    if out["on_off_correlation"] > 1:
        raise ValueError("rig key 'on_off_correlation' must be in [0, 1]")
    if out["hot_pixel_fraction"] > 0.5:
        raise ValueError("rig key 'hot_pixel_fraction' must be in [0, 0.5]")
    if out["sweep_rate_jitter"] > 0.01:
        raise ValueError("rig key 'sweep_rate_jitter' must be in [0, 0.01]")
    if out["hot_pixel_rate_hz"] > 1e5 or out["noise_rate_hz"] > 1e5:
        raise ValueError("event rates above 100 kHz per pixel are not supported")
    try:
        if isinstance(cfg["sweep_curvature_nm"], (bool, str, bytes)):
            raise TypeError
        out["sweep_curvature_nm"] = float(cfg["sweep_curvature_nm"])
    except (TypeError, ValueError):
        raise ValueError("rig key 'sweep_curvature_nm' must be a number") from None
    if not abs(out["sweep_curvature_nm"]) <= 50:
        raise ValueError("rig key 'sweep_curvature_nm' must be within ±50 nm")
    out["band_profile"] = _band_profile(cfg["band_profile"], cfg)
    try:
        if isinstance(cfg["sweep_start_nm"], (bool, str, bytes)):
            raise TypeError
        out["sweep_start_nm"] = float(cfg["sweep_start_nm"])
    except (TypeError, ValueError):
        raise ValueError("rig key 'sweep_start_nm' must be a number") from None
    if not math.isfinite(out["sweep_start_nm"]):
        raise ValueError("rig key 'sweep_start_nm' must be finite")
    if cfg["reset_mode"] not in ("release", "event"):
        raise ValueError(
            f"rig key 'reset_mode' must be 'release' or 'event', got {cfg['reset_mode']!r}"
        )
    seed = cfg["seed"]
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"rig key 'seed' must be a non-negative integer, got {seed!r}")
    gain = cfg["channel_gain"]
    if gain is not None:
        arr = np.asarray(gain)
        if (
            arr.shape != (out["channels"],)
            or not np.issubdtype(arr.dtype, np.number)
            or not np.all(np.isfinite(arr))
            or np.any(arr <= 0)
        ):
            raise ValueError(
                f"rig key 'channel_gain' must be null or {out['channels']} positive "
                "numbers (one per channel)"
            )
    tmap = cfg["threshold_map"]
    if tmap is not None and not isinstance(tmap, str):
        raise ValueError("rig key 'threshold_map' must be null or a file name")
    offs = cfg["column_offsets_us"]
    if offs is not None:
        arr = np.asarray(offs)
        if (
            arr.ndim != 1
            or arr.size == 0
            or not np.issubdtype(arr.dtype, np.number)
            or not np.all(np.isfinite(arr))
        ):
            raise ValueError(
                "rig key 'column_offsets_us' must be null or a non-empty list of "
                "finite numbers (µs), one per sensor column"
            )
        out["column_offsets_us"] = arr.astype(np.float64).tolist()
    return out
