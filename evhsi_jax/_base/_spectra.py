"""Spectral grids and spectra: channels, band integration, resampling, D(λ) and E(λ).

Two grids are used throughout:

- the **channel grid**: `M` equal bins between `channel_start_nm` and `channel_stop_nm`
  (default 72 × 5 nm over 400–760 nm); the reconstruction recovers one value per bin;
- the **fine grid**: each channel split into `sub` equal sub-bins (default 1 nm), on which
  the simulator represents scene spectra, the camera response and the lamp, so that
  structure narrower than a channel (a laser line, a sharp step) is simulated faithfully.

All helpers that prepare data (resampling a user's spectrum, integrating it into bins) are
NumPy: they run once, outside any differentiated path.
"""

from __future__ import annotations

import math

import numpy as np

from ._reference_spectra import reference_spectra

__all__ = [
    "SpectralGrid",
    "band_integrate",
    "band_integrate_matrix",
    "resample",
    "resample_matrix",
    "default_camera_response",
    "default_lamp_spectrum",
]


class SpectralGrid:
    """The channel grid and its fine sub-grid (static configuration, hashable).

    **Arguments:**

    - `channels`: number of channels `M`.
    - `start_nm`, `stop_nm`: the outer edges of the first and last channel, in nm.
    - `fine_step_nm`: target width of the fine sub-bins, in nm; each channel is split into
      `sub = ceil(width / fine_step_nm)` equal parts.
    """

    def __init__(
        self,
        channels: int = 72,
        start_nm: float = 400.0,
        stop_nm: float = 760.0,
        fine_step_nm: float = 1.0,
    ):
        if int(channels) != channels or channels < 2:
            raise ValueError(f"channels must be an integer >= 2, got {channels}")
        if not (math.isfinite(start_nm) and math.isfinite(stop_nm)):
            raise ValueError("channel_start_nm and channel_stop_nm must be finite")
        if not 0 < start_nm < stop_nm:
            raise ValueError(
                f"need 0 < channel_start_nm < channel_stop_nm, got {start_nm}, {stop_nm}"
            )
        if not fine_step_nm > 0:
            raise ValueError(f"fine_step_nm must be > 0, got {fine_step_nm}")
        self.channels = int(channels)
        self.start_nm = float(start_nm)
        self.stop_nm = float(stop_nm)
        self.width_nm = (self.stop_nm - self.start_nm) / self.channels
        self.sub = max(1, math.ceil(self.width_nm / fine_step_nm - 1e-9))
        self.fine_width_nm = self.width_nm / self.sub

    def _key(self):
        return (self.channels, self.start_nm, self.stop_nm, self.sub)

    def __eq__(self, other):
        return isinstance(other, SpectralGrid) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    def __repr__(self):
        return (
            f"SpectralGrid(channels={self.channels}, start_nm={self.start_nm}, "
            f"stop_nm={self.stop_nm}, sub={self.sub})"
        )

    @property
    def edges_nm(self) -> np.ndarray:
        """Channel edges, shape `(M+1,)`."""
        return np.linspace(self.start_nm, self.stop_nm, self.channels + 1)

    @property
    def centres_nm(self) -> np.ndarray:
        """Channel centres, shape `(M,)` — the `wavelengths_nm` of a cube file."""
        e = self.edges_nm
        return 0.5 * (e[1:] + e[:-1])

    @property
    def fine_edges_nm(self) -> np.ndarray:
        """Fine sub-bin edges, shape `(M*sub+1,)`."""
        return np.linspace(self.start_nm, self.stop_nm, self.channels * self.sub + 1)

    @property
    def fine_centres_nm(self) -> np.ndarray:
        """Fine sub-bin centres, shape `(M*sub,)`."""
        e = self.fine_edges_nm
        return 0.5 * (e[1:] + e[:-1])

    def fine_to_channels(self, fine: np.ndarray) -> np.ndarray:
        """Average fine sub-bins into channels along the last axis."""
        fine = np.asarray(fine)
        return fine.reshape(*fine.shape[:-1], self.channels, self.sub).mean(-1)


def _check_spectrum(wavelengths_nm, values, name="spectrum"):
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if wl.ndim != 1 or wl.size < 2:
        raise ValueError(f"{name}: wavelengths_nm must be 1-D with >= 2 samples")
    if v.shape[-1] != wl.size:
        raise ValueError(
            f"{name}: last axis has {v.shape[-1]} samples but "
            f"wavelengths_nm has {wl.size}"
        )
    if not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise ValueError(f"{name}: wavelengths_nm must be finite and increasing")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: values contain NaN or Inf")
    return wl, v


def _require_cover(wl, lo, hi, name):
    # Half a sample of slack: a 5 nm grid ending at 757.5 still covers 760.
    slack = 0.5 * float(np.min(np.diff(wl)))
    if wl[0] > lo + slack or wl[-1] < hi - slack:
        raise ValueError(
            f"{name}: samples span {wl[0]:g}-{wl[-1]:g} nm but {lo:g}-{hi:g} nm "
            "is needed"
        )


def band_integrate_matrix(wavelengths_nm, edges_nm, *, name="spectrum") -> np.ndarray:
    """The linear operator of :func:`band_integrate`, shape `(L, B)`.

    `values @ band_integrate_matrix(wl, edges)` equals `band_integrate(wl, values, edges)`;
    useful when many spectra share one wavelength grid.
    """
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    _check_spectrum(wl, np.zeros(wl.size), name)
    edges = np.asarray(edges_nm, dtype=np.float64)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError("bin edges must be 1-D and increasing")
    _require_cover(wl, edges[0], edges[-1], name)
    # Merge the sample points and the edges; between merged points the interpolant is
    # linear, so the trapezoid rule is exact. Applied to the identity, this gives the
    # operator column by column.
    pts = np.union1d(wl[(wl > edges[0]) & (wl < edges[-1])], edges)
    eye = np.eye(wl.size)
    at = np.stack([np.interp(pts, wl, row) for row in eye])  # (L, P)
    seg = 0.5 * (at[:, 1:] + at[:, :-1]) * np.diff(pts)
    cum = np.concatenate([np.zeros((wl.size, 1)), np.cumsum(seg, axis=1)], 1)
    idx = np.searchsorted(pts, edges)
    return np.diff(cum[:, idx], axis=1) / np.diff(edges)


def band_integrate(wavelengths_nm, values, edges_nm, *, name="spectrum") -> np.ndarray:
    """Mean of a sampled spectrum over each bin.

    The spectrum is the piecewise-linear interpolant of its samples (held constant for at
    most half a sample spacing beyond its ends); the result is its exact integral over
    `[e_i, e_{i+1}]` divided by the bin width.

    **Arguments:**

    - `wavelengths_nm`: sample wavelengths, shape `(L,)`, increasing.
    - `values`: samples, shape `(..., L)`.
    - `edges_nm`: bin edges, shape `(B+1,)`, increasing.

    **Returns:** bin means, shape `(..., B)`.
    """
    wl, v = _check_spectrum(wavelengths_nm, values, name)
    return v @ band_integrate_matrix(wl, edges_nm, name=name)


def resample(wavelengths_nm, values, new_wavelengths_nm, *, name="spectrum"):
    """Linear interpolation of a sampled spectrum onto new wavelengths.

    **Arguments:**

    - `wavelengths_nm`: shape `(L,)`, increasing; `values`: shape `(..., L)`.
    - `new_wavelengths_nm`: shape `(K,)`, inside the sampled range.

    **Returns:** shape `(..., K)`.
    """
    wl, v = _check_spectrum(wavelengths_nm, values, name)
    new = np.asarray(new_wavelengths_nm, dtype=np.float64)
    _require_cover(wl, new.min(), new.max(), name)
    flat = v.reshape(-1, wl.size)
    out = np.stack([np.interp(new, wl, row) for row in flat])
    return out.reshape(*v.shape[:-1], new.size)


def resample_matrix(wavelengths_nm, new_wavelengths_nm, *, name="spectrum"):
    """The linear operator of :func:`resample`, shape `(K, L)`: `values @ W.T` is
    the linear interpolation of spectra sampled at `wavelengths_nm` (L,) onto
    `new_wavelengths_nm` (K,) — two nonzero weights per row, for whole cubes where
    one `np.interp` per spectrum would be slow. The new wavelengths must lie in the
    sampled range with half a sample of slack (as :func:`resample`); in that slack
    the end sample's value is kept (`np.interp`'s clamping), not extrapolated."""
    wl, _ = _check_spectrum(wavelengths_nm, np.zeros(np.size(wavelengths_nm)), name)
    new = np.asarray(new_wavelengths_nm, dtype=np.float64)
    _require_cover(wl, new.min(), new.max(), name)
    return np.stack([np.interp(new, wl, e) for e in np.eye(wl.size)], axis=1)


def default_camera_response(wavelengths_nm) -> np.ndarray:
    """A silicon-like relative quantum efficiency D(λ), peak 1.

    $D(λ) = \\exp(-\\tfrac12((λ-600)/160)^2)$: about 0.46 at 400 nm, 1 at 600 nm and
    0.61 at 760 nm — the broad single hump of a front-illuminated CMOS sensor such as
    the IMX636 (no IR-cut filter inside the 400–760 nm band). It is a documented stand-in;
    replace it with a measured curve through the rig's `camera_response` key.
    """
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    return np.exp(-0.5 * ((wl - 600.0) / 160.0) ** 2)


def _kinoton():
    ref = reference_spectra()
    return ref["lamp_wavelengths_nm"], ref["lamp_values"]


def default_lamp_spectrum(wavelengths_nm) -> np.ndarray:
    """A xenon-arc lamp spectrum E(λ), normalised to peak 1 on the given wavelengths.

    The Kinoton 75P xenon cinema projector lamp shipped with colour-science (380–780 nm,
    2 nm; stored with the package, :mod:`evhsi_jax._base._reference_spectra`), linearly
    interpolated.
    """
    wl, v = _kinoton()
    out = resample(wl, v, wavelengths_nm, name="lamp spectrum")
    return out / out.max()
