"""Frame-camera baseline: the same sweeping rainbow, seen by a conventional camera.

**Capture.** Frame `f` of a sweep is an *instantaneous* sample of the intensity at
$t_f$ (a short exposure; the paper's "uniformly down-sampled frame sequences" of its 1200
simulated intensity frames are exactly this),

$I_f = \\sum_j a_j(λ_c(t_f, τ_x))\\, R_j + c$,

read from the rig's fine band table at the column's band centre $λ_c = λ_0 + βω((t_f
\\bmod P) + τ_x)$, so narrow-band scene structure is seen as by the event simulator. An
optional exposure (`exposure_us`) averages `substeps` samples centred on $t_f$. Frame
times are a uniform subset of the full-bandwidth grid: $t_f = \\lfloor f N / F \\rfloor
P / N$ with $N$ = `rig.samples_per_sweep`, so $F = N$ is the full-bandwidth camera. Noise
is multiplicative Gaussian, $\\tilde I = I (1 + σ n)$, σ = 0.067 (paper), then the frames
are quantised to 8 bits with full scale at the noiseless peak of the stack (the camera's
exposure set to the brightest pixel).

**Reconstruction** (paper supplement 6.5). Each pixel's frames are linearly interpolated
(periodically, in time) onto the band-centre grid of the full-bandwidth camera,
$λ_g$ spaced $βωP/N$ nm; on that grid the design matrix $G_{gm} = A_m(λ_g)$ (the
channel table) is the same for every pixel, so the fit

$\\min_{x \\ge 0} \\|G x - (\\hat I - c)\\|^2 + α\\, \\bar g\\, x^T S x$

($S$ a spectral prior of our method — second differences or high DCT frequencies —
and $\\bar g$ the mean diagonal of $G^TG$)
shares one Gram matrix across all pixels and is solved for all of them at once
(:func:`nonneg_lsq_shared`). With α = 0 — the paper's literal "least squares" — the
problem is a deconvolution of the 17.5 nm band on 5 nm channels: $G^TG$ has condition
number ~$10^{11}$ and 8-bit quantisation alone already ruins the solution, so the
default prior and α are chosen on the training scenes (experiments/bandwidth.py).

:class:`FrameOperator` is the linear map reflectance cube → noiseless frames on the
channel grid (and its adjoint), for tests and for users who want to plug the frame
camera into their own solvers.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .._io import frame_bytes, nominal_event_bytes
from .._model import BandTable, EventStream, Rig, Scene, band_table, lookup
from .._reconstruct import spectral_prior_matrix
from ._nnls import nonneg_lsq_shared

__all__ = [
    "FrameStack",
    "FrameOperator",
    "frame_times_us",
    "frame_intensity",
    "capture_frames",
    "matched_frame_count",
    "reconstruct_frames",
]

#: Multiplicative Gaussian noise of the paper's simulated frame camera (supplement 6.4).
FRAME_NOISE_SIGMA = 0.067
#: Default prior of the frame fit, chosen on the training scenes (`tcs` and the
#: synthetic `sharp` set of experiments/tune_weights.py) at 1200 and 120 frames, by the
#: protocol that chose our reconstruction's weights (experiments/bandwidth.py prints it).
FRAME_ALPHA_SPEC = 3e-2
FRAME_PRIOR_KIND = "d2"


@dataclasses.dataclass(frozen=True, eq=False)
class FrameStack:
    """One sweep seen by a frame camera.

    - `frames`: digital numbers, shape `(F, H, W)`, uint8 for 8 bits (uint16 above).
    - `t_us`: frame (mid-exposure) times within the sweep, µs, shape `(F,)`, increasing.
    - `full_scale`: intensity (white-normalised units of the band table) of the top code.
    - `bits`: bit depth; `exposure_us`: exposure time (0: instantaneous samples).
    """

    frames: np.ndarray
    t_us: np.ndarray
    full_scale: float
    bits: int = 8
    exposure_us: float = 0.0

    @property
    def count(self) -> int:
        return int(self.frames.shape[0])

    @property
    def nbytes(self) -> float:
        """Bandwidth of the stack: `F × H × W × bits / 8` bytes."""
        f, h, w = self.frames.shape
        return frame_bytes(f, w, h, self.bits)

    def intensity(self) -> np.ndarray:
        """The frames back in intensity units, shape `(F, H, W)`, float32."""
        top = 2**self.bits - 1
        return (self.frames.astype(np.float32) * (self.full_scale / top)).astype(
            np.float32
        )


def frame_times_us(rig: Rig, frames: int) -> np.ndarray:
    """Times of `frames` uniformly down-sampled frames within one sweep, µs.

    A subset of the full-bandwidth grid $nP/N$: $t_f = \\lfloor fN/F \\rfloor P/N$.
    """
    n = rig.samples_per_sweep
    if not 1 <= int(frames) <= n:
        raise ValueError(
            f"frames must be in [1, {n}] (samples_per_sweep), got {frames}"
        )
    idx = (np.arange(int(frames)) * n) // int(frames)
    return idx * (float(rig.period_us) / n)


def frame_intensity(
    scene: Scene,
    rig: Rig,
    t_us: np.ndarray,
    *,
    exposure_us: float = 0.0,
    substeps: int = 8,
) -> Float[Array, "f h w"]:
    """Noiseless intensity of every pixel at the frame times (fine-grid physics).

    **Arguments:**

    - `scene`: the reflectance scene.
    - `rig`: the rig (band table, β, λ0, τx, c).
    - `t_us`: frame times in µs, shape `(F,)` (taken modulo the sweep period).
    - `exposure_us`: exposure per frame; 0 samples the intensity at `t_us`.
    - `substeps`: samples averaged over a non-zero exposure.

    **Returns:** intensity `(F, H, W)` in the band table's units (a white pixel peaks
    at 1 + c).
    """
    if exposure_us < 0:
        raise ValueError(f"exposure_us must be >= 0, got {exposure_us}")
    fine = band_table(rig)
    # Table of each palette spectrum's response to a band at λc (interpolation in λc
    # commutes with the sum over sub-bins, so this is exact for the simulator's table).
    pal = scene.palette_on(rig.grid.fine_edges_nm)  # (K, Mf)
    tab = jnp.asarray(np.asarray(fine.values, np.float64) @ pal.T, fine.values.dtype)
    offsets = rig.column_offsets(scene.width)
    t = np.asarray(t_us, np.float64)
    steps = int(substeps) if exposure_us > 0 else 1
    frac = (np.arange(steps) + 0.5) / steps - 0.5
    ts = (t[:, None] + exposure_us * frac[None, :]).reshape(-1)  # (F·S,)
    inten = _intensity_kernel(
        rig,
        BandTable(tab, fine.lo_nm, fine.step_nm),
        jnp.asarray(ts, offsets.dtype),
        offsets,
        jnp.asarray(scene.labels),
    )
    inten = inten.reshape(t.shape[0], steps, scene.height, scene.width).mean(1)
    return inten + rig.baseline_rel


@eqx.filter_jit
def _intensity_kernel(rig, table, ts, offsets, labels):
    def column(off, lab):  # one column: (F·S,) times → (F·S, H)
        return lookup(table, rig.band_centre_nm(ts, off))[:, lab]

    return jax.vmap(column, in_axes=(0, 1), out_axes=2)(offsets, labels)


class FrameOperator(eqx.Module):
    """Channel-grid frame model $y_{f,h,w} = \\sum_m A_m(λ_c(t_f, τ_w))\\, x_{h,w,m}$.

    `table[w, f, m]` holds the channel table read at column `w`'s band centre at frame
    time `f`; the constant light c is left out (the map is linear).
    """

    table: Float[Array, "w f wl"]

    @classmethod
    def from_rig(cls, rig: Rig, t_us, width: int) -> FrameOperator:
        """The operator for frames at `t_us` (µs) of a sensor `width` columns wide."""
        chan = band_table(rig).channels(rig.grid.sub)
        offsets = rig.column_offsets(width)
        t = jnp.asarray(np.asarray(t_us, np.float64), offsets.dtype)
        centres = rig.band_centre_nm(t[None, :], offsets[:, None])  # (w, f)
        return cls(lookup(chan, centres))

    def __call__(
        self, cube: Float[Array | np.ndarray, "h w wl"]
    ) -> Float[Array, "f h w"]:
        return jnp.einsum("wfm,hwm->fhw", self.table, cube)

    def adjoint(
        self, frames: Float[Array | np.ndarray, "f h w"]
    ) -> Float[Array, "h w wl"]:
        return jnp.einsum("wfm,fhw->hwm", self.table, frames)


def capture_frames(
    scene: Scene,
    rig: Rig,
    *,
    frames: int,
    noise_sigma: float = FRAME_NOISE_SIGMA,
    bits: int = 8,
    exposure_us: float = 0.0,
    full_scale: float | None = None,
    key: PRNGKeyArray,
) -> FrameStack:
    """Simulate a frame camera capturing one sweep of the rainbow.

    **Arguments:**

    - `scene`, `rig`: what is seen, under which illumination.
    - `frames`: frames per sweep, uniformly down-sampled from `rig.samples_per_sweep`.
    - `noise_sigma`: multiplicative Gaussian noise σ (paper: 0.067); 0 for none.
    - `bits`: quantisation depth (paper: 8).
    - `exposure_us`: exposure per frame (0: instantaneous samples, the default).
    - `full_scale`: intensity of the top code; default the noiseless peak of the stack.
    - `key`: PRNG key for the noise.

    **Returns:** a :class:`FrameStack`.
    """
    if not 1 <= int(bits) <= 16:
        raise ValueError(f"bits must be in [1, 16], got {bits}")
    if noise_sigma < 0:
        raise ValueError(f"noise_sigma must be >= 0, got {noise_sigma}")
    t = frame_times_us(rig, frames)
    clean = frame_intensity(scene, rig, t, exposure_us=exposure_us)
    scale = float(jnp.max(clean)) if full_scale is None else float(full_scale)
    if not scale > 0:
        raise ValueError(f"full_scale must be > 0, got {scale}")
    # NumPy draws (seeded from the key): a new frame count then costs no compilation.
    rng = np.random.default_rng(np.asarray(jr.key_data(key)).ravel().tolist())
    clean = np.asarray(clean, np.float64)
    noisy = clean * (1.0 + noise_sigma * rng.standard_normal(clean.shape))
    top = 2 ** int(bits) - 1
    dn = np.clip(np.round(noisy / scale * top), 0, top)
    dn = dn.astype(np.uint8 if bits <= 8 else np.uint16)
    return FrameStack(dn, t, scale, int(bits), float(exposure_us))


def matched_frame_count(
    events: EventStream | int,
    width: int | None = None,
    height: int | None = None,
    *,
    sweeps: int = 1,
    bits_per_event: int = 16,
    bits_per_pixel: int = 8,
) -> int:
    """Frames per sweep that cost as many bytes as the events (paper supplement 6.5).

    $F = \\mathrm{round}(n_{ev} \\cdot b_{ev} / (H W b_{px}) / \\text{sweeps})$, at least 1.

    **Arguments:**

    - `events`: the event stream, or an event count (then give `width`, `height`).
    - `sweeps`: sweeps the events span.
    - `bits_per_event`: 16 (EVT 3.0, as the paper counts); `bits_per_pixel`: 8.

    **Returns:** the bandwidth-matched frame count per sweep.
    """
    if isinstance(events, EventStream):
        n, width, height = len(events), events.width, events.height
    else:
        n = int(events)
        if width is None or height is None:
            raise ValueError("give width and height with an event count")
    if sweeps < 1:
        raise ValueError(f"sweeps must be >= 1, got {sweeps}")
    ev_bytes = nominal_event_bytes(n, bits_per_event)
    per_frame = frame_bytes(1, width, height, bits_per_pixel)
    return max(1, int(round(ev_bytes / per_frame / sweeps)))


def _design(rig: Rig) -> tuple[Float[Array, "g wl"], np.ndarray]:
    """The shared design matrix on the full-bandwidth band-centre grid, and the grid."""
    table = band_table(rig).channels(rig.grid.sub)
    step = float(rig.band_speed_nm_per_us * rig.period_us)
    step /= rig.samples_per_sweep
    hi = table.lo_nm + table.step_nm * (table.values.shape[0] - 1)
    lam = table.lo_nm + step * np.arange(int(math.floor((hi - table.lo_nm) / step)) + 1)
    return lookup(table, jnp.asarray(lam, table.values.dtype)), lam


def interpolate_traces(
    stack: FrameStack, rig: Rig, lam_nm: np.ndarray
) -> Float[Array, "h w g"]:
    """Each pixel's frames, linearly interpolated (periodically) onto band centres."""
    inten = jnp.asarray(stack.intensity())  # (F, H, W)
    speed = float(rig.band_speed_nm_per_us)
    offsets = rig.column_offsets(inten.shape[2]).astype(inten.dtype)
    t_g = jnp.asarray((lam_nm - float(rig.sweep_start_nm)) / speed, inten.dtype)
    t_f = jnp.asarray(stack.t_us, inten.dtype)
    return _interp_kernel(inten, t_f, t_g, offsets, float(rig.period_us))


@functools.partial(jax.jit, static_argnames="period")
def _interp_kernel(inten, t_f, t_g, offsets, period):
    def pixel(trace, off):
        return jnp.interp(t_g - off, t_f, trace, period=period)

    per_col = jax.vmap(pixel, in_axes=(1, None))  # over rows of a column
    return jax.vmap(per_col, in_axes=(2, 0), out_axes=1)(inten, offsets)


def reconstruct_frames(
    stack: FrameStack,
    rig: Rig,
    *,
    nonneg: bool = True,
    alpha_spec: float = FRAME_ALPHA_SPEC,
    prior_kind: str = FRAME_PRIOR_KIND,
    m_start_frac: float = 0.3,
    iters: int = 1500,
    chunk_pixels: int = 4096,
) -> Float[np.ndarray, "h w wl"]:
    """Least-squares spectra from frames, linearly interpolated in time (paper 6.5).

    **Arguments:**

    - `stack`: the frames of one sweep (:func:`capture_frames`).
    - `rig`: the calibration (band table, β, λ0, τx, c), as for the events.
    - `nonneg`: enforce x ≥ 0 (default); False solves the unconstrained least squares.
    - `alpha_spec`: weight α of the DCT high-frequency prior, relative to the mean
      diagonal of $G^TG$ (0: plain least squares, ill-posed — see the module doc).
    - `prior_kind`: `"d2"` (second differences) or `"dct"` (the paper's high DCT
      frequencies) — the same priors as :func:`evhsi_jax.reconstruction.spectral_prior_matrix`.
    - `m_start_frac`: cut-off frequency of the prior as a fraction of M.
    - `iters`: ADMM iterations (with `nonneg`; ~1e-4 max error after 1000 for
      α ≥ 1e-4).
    - `chunk_pixels`: pixels solved per batch.

    **Returns:** the cube `(H, W, M)`, float32 reflectance.
    """
    g_mat, lam = _design(rig)
    traces = interpolate_traces(stack, rig, lam)  # (H, W, G)
    h, w, _ = traces.shape
    b = traces.reshape(h * w, -1) - rig.baseline_rel.astype(traces.dtype)
    g_mat = g_mat.astype(traces.dtype)
    q_mat = g_mat.T @ g_mat
    m = q_mat.shape[0]
    if alpha_spec > 0:
        prior = spectral_prior_matrix(m, m_start_frac, prior_kind)
        prior = jnp.asarray(prior, q_mat.dtype)
        q_mat = q_mat + alpha_spec * jnp.mean(jnp.diag(q_mat)) * prior
    q_vec = b @ g_mat  # (P, M)
    if not nonneg:
        ridge = 1e-7 * jnp.mean(jnp.diag(q_mat)) * jnp.eye(m, dtype=q_mat.dtype)
        x = jnp.linalg.solve(q_mat + ridge, q_vec.T).T
        return np.asarray(x, np.float32).reshape(h, w, m)
    n = h * w
    chunk = min(int(chunk_pixels), n)
    pad = (-n) % chunk  # one compiled shape for every chunk
    q_vec = jnp.concatenate([q_vec, jnp.zeros((pad, m), q_vec.dtype)])
    out = [
        nonneg_lsq_shared(q_mat, qv, iters=int(iters))
        for qv in jnp.split(q_vec, q_vec.shape[0] // chunk)
    ]
    x = jnp.concatenate(out)[:n]
    return np.asarray(x, np.float32).reshape(h, w, m)
