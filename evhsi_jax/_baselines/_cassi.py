"""Single-disperser coded-aperture snapshot spectral imaging (SD-CASSI), simulated.

A coded aperture (a random binary mask $Φ$) sits in an image plane; a disperser then
shears the coded cube along x by `shift_px` pixels per channel, and a monochrome
detector integrates over wavelength (Wagadarikar et al. 2008):

$y_{i,j} = \\sum_m Φ_{i,\\,j - s m}\\; x_{i,\\,j - s m,\\,m}$,  $y \\in
\\mathbb{R}^{H \\times (W + s(M-1))}$.

The forward operator is a scatter-add of the masked cube, its adjoint the matching
gather, $(A^Ty)_{i,j,m} = Φ_{i,j}\\, y_{i, j + s m}$. $AA^T$ is diagonal,
$R_{i,j} = \\sum_m Φ^2_{i, j - s m}$ — what GAP's Euclidean projection divides by.

Simplifications (documented choices): the detector sees the reflectance cube directly
(flat illumination and response on the channel grid, i.e. after a white calibration), no
optical blur, an exact one-pixel shear per channel; optional measurement noise in the
style of the frame camera (multiplicative Gaussian, then 8-bit quantisation).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

__all__ = ["CassiOperator", "random_mask", "cassi_measure"]


def random_mask(
    height: int, width: int, *, fill: float = 0.5, key: PRNGKeyArray
) -> Float[Array, "h w"]:
    """A random binary coded aperture: each pixel open with probability `fill`."""
    if not 0 < fill <= 1:
        raise ValueError(f"fill must be in (0, 1], got {fill}")
    return jr.bernoulli(key, fill, (height, width)).astype(float)


class CassiOperator(eqx.Module):
    """The SD-CASSI forward model for one mask: call it, or take its `adjoint`.

    **Arguments:**

    - `mask`: the coded aperture $Φ$, shape `(H, W)` (binary or grey).
    - `channels`: number of spectral channels M.
    - `shift_px`: dispersion per channel along x, in pixels (s ≥ 0).
    """

    mask: Float[Array, "h w"]
    channels: int = eqx.field(static=True)
    shift_px: int = eqx.field(static=True)

    def __init__(self, mask, channels: int, shift_px: int = 1):
        mask = jnp.asarray(mask)
        if mask.ndim != 2:
            raise ValueError(f"mask must be (H, W), got shape {mask.shape}")
        if channels < 1 or shift_px < 0:
            raise ValueError("need channels >= 1 and shift_px >= 0")
        self.mask = mask
        self.channels = int(channels)
        self.shift_px = int(shift_px)

    @property
    def cube_shape(self) -> tuple[int, int, int]:
        h, w = self.mask.shape
        return h, w, self.channels

    @property
    def measurement_shape(self) -> tuple[int, int]:
        h, w = self.mask.shape
        return h, w + self.shift_px * (self.channels - 1)

    def _columns(self):
        w = self.mask.shape[1]
        return jnp.arange(w)[:, None] + self.shift_px * jnp.arange(self.channels)

    def __call__(
        self, cube: Float[Array | np.ndarray, "h w wl"]
    ) -> Float[Array, "h wy"]:
        """$y = A x$: mask, shear along x, sum over channels."""
        coded = self.mask[..., None].astype(cube.dtype) * cube
        y = jnp.zeros(self.measurement_shape, cube.dtype)
        return y.at[:, self._columns()].add(coded)

    def adjoint(self, y: Float[Array | np.ndarray, "h wy"]) -> Float[Array, "h w wl"]:
        """$A^T y$: un-shear (gather each channel's columns), mask."""
        return self.mask[..., None].astype(y.dtype) * y[:, self._columns()]

    def normaliser(self) -> Float[Array, "h wy"]:
        """The diagonal of $AA^T$, $R = \\sum_m Φ^2$ sheared; where R = 0 (no open
        pixel maps there) it is set to 1 so that divisions by it are safe."""
        r = self(jnp.broadcast_to(self.mask[..., None], self.cube_shape))  # Σ Φ·Φ
        return jnp.where(r > 0, r, 1.0)


def cassi_measure(
    cube: Float[Array | np.ndarray, "h w wl"],
    op: CassiOperator,
    *,
    noise_sigma: float = 0.0,
    bits: int | None = None,
    key: PRNGKeyArray | None = None,
) -> Float[Array, "h wy"]:
    """A CASSI snapshot of `cube`, optionally with frame-camera noise.

    **Arguments:**

    - `cube`: reflectance, shape `(H, W, M)`.
    - `op`: the :class:`CassiOperator`.
    - `noise_sigma`: multiplicative Gaussian noise σ (0: noiseless).
    - `bits`: quantise to this depth with full scale at the noiseless peak (None: not).
    - `key`: PRNG key (needed when `noise_sigma > 0`).

    **Returns:** the measurement, shape `op.measurement_shape`, in cube units.
    """
    y = op(jnp.asarray(cube))
    if noise_sigma > 0:
        if key is None:
            raise ValueError("a key is needed for noise_sigma > 0")
        y = y * (1.0 + noise_sigma * jr.normal(key, y.shape, y.dtype))
    if bits is not None:
        top = 2 ** int(bits) - 1
        peak = jnp.max(op(jnp.asarray(cube)))
        y = jnp.clip(jnp.round(y / peak * top), 0, top) * (peak / top)
    return y
