"""The sweeping rainbow: band profile, the A(λc) table and per-column time tables.

The swept band has a Gaussian profile of the rig's FWHM with peak 1 (a wider slit passes
more light, so the band's peak spectral radiance stays E(λ) while its power grows with the
FWHM). A pixel of fine-grid reflectance $R_f$ receives

$I(t) = g \\sum_f D_f E_f R_f \\int_{\\text{sub-bin } f} T(λ - λ_c(t))\\,dλ + c$,

integrated exactly (erf differences) for spectra that are constant on each fine sub-bin.
The gain $g$ normalises the peak over $λ_c$ of a reflectance-1 pixel to 1, so the constant
light $c$ = `baseline_rel` and ε = `log_eps` are fractions of that peak, and only ratios
matter — as for the sensor, which sees log-intensity.

Everything here is a pure function of the rig's leaves, differentiable in FWHM, β, λ0,
τx, D(λ), E(λ) and c. The band profile depends only on the band centre λc, so the
response is tabulated once over λc (0.1 nm steps) and linearly interpolated: that is what
makes a 1280-column sensor cheap (every column reads the same table).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import jax.scipy.special as jsp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._rig import Rig

__all__ = [
    "BandTable",
    "band_table",
    "lookup",
    "fwhm_to_sigma",
    "column_time_table",
]

_SQRT2 = np.sqrt(2.0)
TABLE_STEP_NM = 0.1
#: Bands up to this FWHM share one table range (3 × 50 nm beyond the channels), also
#: when the FWHM is traced.
TRACED_FWHM_BOUND_NM = 50.0
#: `BandTable.trimmed`'s default: a band's entries below this fraction of its own
#: peak count as zero (about one float32 ulp of the peak). The reconstruction's fused
#: CPU kernel and CUDA kernel work on the channels a row touches, and a Gaussian's
#: float32 tails reach ~28 channels where 1e-7 of the peak leaves ~16.
BAND_TRIM = 1e-7


def fwhm_to_sigma(fwhm_nm):
    """Gaussian σ from FWHM: $σ = \\mathrm{FWHM}/(2\\sqrt{2\\ln 2})$."""
    return fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def table_range_nm(rig: Rig, fwhm_bound_nm: float | None = None) -> tuple[float, float]:
    """Static λc range of the table: the channel range widened by 3 × max(FWHM, 50 nm).

    Beyond it the band overlaps the channel range by less than $10^{-10}$ of its peak.
    For every FWHM up to 50 nm the range is the same, so a rig whose FWHM is traced
    (differentiated) gets exactly the table of the same rig evaluated concretely —
    gradients then match finite differences. `fwhm_bound_nm` widens it for broader
    bands (static).
    """
    if fwhm_bound_nm is not None:
        fwhm = float(fwhm_bound_nm)
    else:
        try:
            fwhm = float(rig.fwhm_nm)
        except jax.errors.ConcretizationTypeError:  # traced (being differentiated)
            fwhm = TRACED_FWHM_BOUND_NM
    margin = 3.0 * max(fwhm, TRACED_FWHM_BOUND_NM)
    return rig.grid.start_nm - margin, rig.grid.stop_nm + margin


@dataclasses.dataclass(frozen=True)
class BandTable:
    """Response of each fine sub-bin (or channel) to a band centred at λc.

    `values[i, f]` is the intensity a reflectance-1 sub-bin `f` contributes when the band
    centre is `lo_nm + i * step_nm` (zero outside the table). (A table that carries
    its tangents has one more axis: :func:`lookup_tangents`.)
    """

    values: Float[Array, "n f *tangents"]
    lo_nm: float
    step_nm: float

    def channels(self, sub: int) -> BandTable:
        """Sum the fine sub-bins into channels: the reconstruction's A(λc) table."""
        return BandTable(_sum_sub_bins(self.values, sub), self.lo_nm, self.step_nm)

    def trimmed(self, rel: float = BAND_TRIM) -> BandTable:
        """The table with each band's entries (row `i`) below `rel` of that band's
        largest magnitude set to zero: what the reconstruction's span-based kernels
        solve with (:mod:`evhsi_jax._reconstruct._fused`)."""
        return BandTable(trim_rows(self.values, rel), self.lo_nm, self.step_nm)


@functools.partial(jax.jit, static_argnums=1)  # one compiled call, not two eager ops
def _sum_sub_bins(v, sub: int):
    return v.reshape(v.shape[0], v.shape[1] // sub, sub).sum(-1)


def trim_rows(v, rel: float = BAND_TRIM):
    """`v` `(n, M)` with each row's entries below `rel` of the row's largest magnitude
    set to zero (`BandTable.trimmed`'s values): in NumPy for a NumPy array (the fused
    CPU kernel's float64 copy of a table: no compilation), else one compiled JAX
    call."""
    if isinstance(v, np.ndarray):
        a = np.abs(v)
        return np.where(a > rel * a.max(axis=1, keepdims=True), v, 0.0).astype(v.dtype)
    return _trim_rows_jax(v, rel)


@jax.jit
def _trim_rows_jax(v, rel):
    a = jnp.abs(v)
    return jnp.where(a > rel * jnp.max(a, axis=1, keepdims=True), v, jnp.zeros_like(v))


jax.tree_util.register_dataclass(
    BandTable, data_fields=["values"], meta_fields=["lo_nm", "step_nm"]
)


def band_table(rig: Rig, *, fwhm_bound_nm: float | None = None) -> BandTable:
    """Tabulate the band response over λc for the rig's fine grid.

    **Arguments:**

    - `rig`: the rig (FWHM, D, E are read; differentiable).
    - `fwhm_bound_nm`: a static upper bound on the FWHM, needed when the rig's FWHM is
      traced (inside `jit`/`grad`) since the table's size must be static.

    **Returns:** a :class:`BandTable` with `values` of shape `(n, M*sub)`.
    """
    overlap = band_overlap(rig, fwhm_bound_nm=fwhm_bound_nm)
    weight = rig.camera_response * rig.lamp
    raw = overlap.values * weight[None, :]
    gain = 1.0 / jnp.max(jnp.sum(raw, axis=1))
    return BandTable(raw * gain, overlap.lo_nm, overlap.step_nm)


def band_overlap(rig: Rig, *, fwhm_bound_nm: float | None = None) -> BandTable:
    """The band's overlap with each fine sub-bin over λc, before the camera response
    and lamp weigh it (`band_table` = this × D·E, normalised). It depends on the band
    alone (FWHM or profile), so a fit that keeps the band fixed computes it once."""
    lo, hi = table_range_nm(rig, fwhm_bound_nm)
    n = int(np.ceil((hi - lo) / TABLE_STEP_NM)) + 1
    centres = lo + TABLE_STEP_NM * jnp.arange(n, dtype=rig.fwhm_nm.dtype)
    edges = jnp.asarray(rig.grid.fine_edges_nm, dtype=rig.fwhm_nm.dtype)
    if rig.band_profile is not None:
        overlap = _profile_overlap(rig.band_profile, edges, centres)
    else:
        overlap = _gaussian_overlap(rig.fwhm_nm, edges, centres)
    return BandTable(overlap, lo, TABLE_STEP_NM)


def _profile_overlap(profile, edges, centres):
    """∫ T(λ - λc) dλ over each sub-bin for a sampled profile T (piecewise linear):
    differences of its cumulative integral G, $G(e_{f+1} - λ_c) - G(e_f - λ_c)$."""
    off = np.asarray(profile[0], np.float64)
    val = np.asarray(profile[1], np.float64)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (val[1:] + val[:-1]) * np.diff(off))])
    dtype = centres.dtype
    return _differenced(jnp.asarray(off, dtype), jnp.asarray(cum, dtype), edges, centres)


def _differenced(off, cum, edges, centres):
    """The cumulative integral `cum` (at offsets `off`) interpolated at every edge
    minus centre, differenced over each sub-bin: the `(n, F)` overlap table."""
    g = jnp.interp(edges[None, :] - centres[:, None], off, cum)
    return g[:, 1:] - g[:, :-1]


def sampled_profile_overlap(offsets_nm, values, edges_nm, lo_nm, step_nm, n):
    """:func:`_profile_overlap` over the table's λc grid (`n` centres from `lo_nm` in
    steps of `step_nm`), with the profile's samples `values` an array that may be
    traced (the calibration fits them, `fit_band`): the same piecewise-linear
    profile's cumulative integral, in `values`' dtype, differenced over each sub-bin.
    `offsets_nm` and the sub-bin edges `edges_nm` are fixed (host arrays).

    When the edges lie on the λc grid (the default rig's: 1 nm and 0.1 nm), every
    entry's offset λ − λc is a multiple of the step, so the cumulative integral is
    interpolated once per distinct offset (~10⁴) and the table gathered from those
    instead of searched per entry (3.7× faster in float64)."""
    cum, off = _cumulative(offsets_nm, values)
    k = _grid_edges(edges_nm, lo_nm, step_nm)
    if k is None:
        return _interpolated_overlap(off, cum, edges_nm, lo_nm, step_nm, n)
    g, k0 = _cumulative_at_offsets(off, cum, k, step_nm, n)
    table = g[(k[None, :] - np.arange(n)[:, None] - k0).astype(np.int32)]
    return table[:, 1:] - table[:, :-1]


def sampled_profile_product(offsets_nm, values, edges_nm, lo_nm, step_nm, n, weights):
    """`sampled_profile_overlap(...) @ weights` (`weights`: `(F, C)`, one row per
    sub-bin) without forming the `(n, F)` table: what the calibration needs while it
    fits the band (the traces of the chart's spectra are the table times their
    weighted spectra), and its derivatives along each band parameter.

    On the λc grid with evenly spaced edges (`d` table steps apart), entry `i` of the
    product is $\\sum_e G(k_e - i) H_e$, with $G$ the profile's cumulative integral
    at the grid's offsets and $H_e = w_{e-1} - w_e$ the sub-bins' weights differenced
    at edge `e`. For the `i` of one residue modulo `d` that is a correlation of every
    `d`-th value of $G$ with $H$: `d` one-dimensional convolutions, no gather of the
    table. The table's tangent along one band parameter cost ~12 ms (a 2.4 M-entry
    gather, float64, 2 cores); the convolution ~3 ms. Elsewhere (edges off the grid
    or uneven): the table times `weights`."""
    cum, off = _cumulative(offsets_nm, values)
    k = _grid_edges(edges_nm, lo_nm, step_nm)
    d = int(k[1] - k[0]) if k is not None and k.size > 1 else 0
    if k is None or d < 1 or np.any(np.diff(k) != d):
        return sampled_profile_overlap(
            offsets_nm, values, edges_nm, lo_nm, step_nm, n
        ) @ jnp.asarray(weights, values.dtype)
    weights = jnp.asarray(weights, values.dtype)
    g, _ = _cumulative_at_offsets(off, cum, k, step_nm, n)  # g[j]: offset k0 + j
    c = weights.shape[1]
    zero = jnp.zeros((1, c), weights.dtype)
    h = jnp.concatenate([zero, weights]) - jnp.concatenate([weights, zero])  # (F+1, C)
    f_edges = k.size  # F + 1
    q = -(-n // d)  # outputs per residue
    # Residue r, output q (reversed: q' = q - 1 - q_idx) reads g at
    # n - 1 - r - d (q - 1) + d (p), p = q' + e: left padding `d` keeps it >= 0 (the
    # reads below 0 only feed outputs past `n`, which are dropped).
    r = np.arange(d)[:, None]
    p = np.arange(f_edges + q - 1)[None, :]
    idx = d + (n - 1) - r - d * (q - 1) + d * p
    gp = jnp.concatenate([jnp.zeros((d,), g.dtype), g])
    a = gp[idx.astype(np.int32)][:, None, :]  # (d, 1, F + q)
    out = jax.lax.conv_general_dilated(
        a, h.T[:, None, :], (1,), "VALID", precision=jax.lax.Precision.HIGHEST
    )  # (d, C, q): out[r, :, q'] is entry d (q - 1 - q') + r
    out = jnp.transpose(out[:, :, ::-1], (2, 0, 1)).reshape(q * d, c)
    return out[:n]


def _cumulative(offsets_nm, values):
    """The piecewise-linear profile's cumulative integral at its offsets (trapezoids),
    in `values`' dtype, and the offsets as an array of that dtype."""
    off = jnp.asarray(offsets_nm, values.dtype)
    area = 0.5 * (values[1:] + values[:-1]) * jnp.diff(off)
    return jnp.concatenate([jnp.zeros((1,), values.dtype), jnp.cumsum(area)]), off


def _grid_edges(edges_nm, lo_nm, step_nm):
    """The sub-bin edges in table steps from `lo_nm` (integers), or None when they
    are not on the λc grid."""
    k = (np.asarray(edges_nm, np.float64) - lo_nm) / step_nm
    if not np.allclose(k, np.round(k), rtol=0.0, atol=1e-6):
        return None
    return np.round(k).astype(np.int64)


def _cumulative_at_offsets(off, cum, k, step_nm, n):
    """The cumulative integral at every offset `k_e - i` (in table steps) of the
    table, from the smallest `k0 = k[0] - (n - 1)`: `(g, k0)`, `g[j]` at `k0 + j`."""
    k0 = int(k[0]) - (n - 1)
    grid = jnp.asarray(step_nm * np.arange(k0, int(k[-1]) + 1), cum.dtype)
    return jnp.interp(grid, off, cum), k0


def _interpolated_overlap(off, cum, edges_nm, lo_nm, step_nm, n):
    """The overlap table interpolated entry by entry (edges off the λc grid)."""
    dtype = cum.dtype
    centres = lo_nm + step_nm * jnp.arange(n, dtype=dtype)
    edges = jnp.asarray(np.asarray(edges_nm, np.float64), dtype)
    return _differenced(off, cum, edges, centres)


def _gaussian_overlap(fwhm_nm, edges, centres):
    sigma = fwhm_to_sigma(fwhm_nm)
    # ∫ exp(-(λ-λc)²/2σ²) dλ over [e_f, e_f+1] = σ√(π/2) [erf(u_f+1) - erf(u_f)].
    u = (edges[None, :] - centres[:, None]) / (sigma * _SQRT2)
    ua, ub = u[:, :-1], u[:, 1:]
    # erf(ub) - erf(ua) cancels catastrophically in float32 in the tails (both near
    # ±1; it even turns negative): difference the complementary function of the side
    # the sub-bin lies on instead, accurate and >= 0 down to underflow.
    upper = (ua + ub) > 0
    diff = jnp.where(
        upper, jsp.erfc(ua) - jsp.erfc(ub), jsp.erfc(-ub) - jsp.erfc(-ua)
    )
    return sigma * np.sqrt(np.pi / 2.0) * diff


def lookup(
    table: BandTable,
    centre_nm: Float[Array, "..."],
    *,
    order: int = 1,
    column: Int[Array, "..."] | None = None,
) -> Float[Array, "..."]:
    """Interpolate the table at band centres `centre_nm` (any shape).

    Returns shape `centre_nm.shape + (f,)`; with `column` (integer indices broadcastable
    to `centre_nm`), only that column of the table at each point, shape
    `centre_nm.shape` — f times less work and memory (under autodiff too) when each
    point needs one column.

    Outside the table the response is zero. `order=1` is linear (value error ~2e-5 of
    the peak at 0.1 nm steps, derivative piecewise constant); `order=3` is cubic Hermite
    with Catmull–Rom slopes, whose derivative is continuous — what a Gauss–Newton fit of
    time offsets needs, since with linear interpolation the residuals have kinks every
    table step (≈ 6 µs of sweep time at the default β). Differentiable in `centre_nm`
    and in the table values.
    """
    if order not in (1, 3):
        raise ValueError(f"order must be 1 or 3, got {order}")
    n = table.values.shape[0]
    i0, inside = _stencil(table, centre_nm)
    if column is None:
        points = [table.values[i] for i in _points(i0, n, order)]
        v = _interpolate(points, _fraction(table, centre_nm, i0)[..., None], order)
        return jnp.where(inside[..., None], v, 0.0)
    col = jnp.broadcast_to(column, i0.shape)
    points = [table.values[i, col] for i in _points(i0, n, order)]
    v = _interpolate(points, _fraction(table, centre_nm, i0), order)
    return jnp.where(inside, v, 0.0)


def lookup_tangents(
    table: BandTable,
    centre_nm: Float[Array, "..."],
    d_centre_nm: Float[Array, "t ..."],
    *,
    column: Int[Array, "..."],
    order: int = 3,
) -> tuple[Float[Array, "..."], Float[Array, "t ..."]]:
    """:func:`lookup` (one column per point) and its tangents along T directions at
    once: `(value, d_value)`, `d_value` of shape `(T,) + centre_nm.shape`.

    `table.values` carries a trailing axis of 1 + T: `[..., 0]` the table, `[..., 1:]`
    its tangents; `d_centre_nm` (`(T,) + centre_nm.shape`) the centres' tangents.
    Equal to `jax.jvp` of :func:`lookup` along each direction, but each stencil point
    is gathered once for the table and all its tangents (a row of 1 + T values):
    JAX's derivative of a lookup gathers again per direction, and on XLA's CPU
    backend those gathers were most of a chart fit's Gauss–Newton pass (2026-12-08).
    """
    if order not in (1, 3):
        raise ValueError(f"order must be 1 or 3, got {order}")
    n = table.values.shape[0]
    i0, inside = _stencil(table, centre_nm)
    col = jnp.broadcast_to(column, i0.shape)
    rows = [table.values[i, col] for i in _points(i0, n, order)]  # each (..., 1 + T)
    points = [r[..., 0] for r in rows]
    d_points = [jnp.moveaxis(r[..., 1:], -1, 0) for r in rows]

    def value(points, centre):
        return _interpolate(points, _fraction(table, centre, i0), order)

    v, lin = jax.linearize(value, points, centre_nm)
    dv = jax.vmap(lin)(d_points, d_centre_nm)
    return jnp.where(inside, v, 0.0), jnp.where(inside, dv, 0.0)


def _stencil(table: BandTable, centre_nm):
    """The interpolation's first point (the table row at or below each centre, at most
    the last but one) and whether the centre lies on the table."""
    n = table.values.shape[0]
    pos = (centre_nm - table.lo_nm) / table.step_nm
    inside = (pos >= 0) & (pos <= n - 1)
    i0f = jnp.clip(jnp.floor(jnp.clip(pos, 0, n - 1)), 0, n - 2)
    return i0f.astype(jnp.int32), inside


def _fraction(table: BandTable, centre_nm, i0):
    """Each centre's position past its first point, in table steps (differentiable in
    the centre; `i0` from :func:`_stencil`)."""
    n = table.values.shape[0]
    pos = jnp.clip((centre_nm - table.lo_nm) / table.step_nm, 0, n - 1)
    return pos - i0.astype(pos.dtype)


def _points(i0, n: int, order: int):
    """The rows the interpolation reads: 2 (linear) or 4 (cubic; clamped at the ends)."""
    if order == 1:
        return [i0, i0 + 1]
    return [jnp.maximum(i0 - 1, 0), i0, i0 + 1, jnp.minimum(i0 + 2, n - 1)]


def _interpolate(points, frac, order: int):
    """Linear, or cubic Hermite with Catmull–Rom slopes, between the middle points."""
    if order == 1:
        return points[0] * (1 - frac) + points[1] * frac
    p0, p1, p2, p3 = points
    m1, m2 = 0.5 * (p2 - p0), 0.5 * (p3 - p1)
    f2, f3 = frac * frac, frac * frac * frac
    return (
        (2 * f3 - 3 * f2 + 1) * p1
        + (f3 - 2 * f2 + frac) * m1
        + (-2 * f3 + 3 * f2) * p2
        + (f3 - f2) * m2
    )


def column_time_table(
    rig: Rig,
    table: BandTable,
    t_us: Float[Array, " t"],
    column_offset_us: Float[ArrayLike, ""],
) -> Float[Array, "t f"]:
    """A(t) for one column (paper Eq. 6): the table read at $λ_c(t + τ_x)$.

    **Arguments:**

    - `t_us`: times in µs (taken modulo the sweep period), shape `(t,)`.
    - `column_offset_us`: τx of the column, µs.

    **Returns:** shape `(t, f)` — one row per time, one column per table bin (fine
    sub-bins, or channels for a channel table).
    """
    return lookup(table, rig.band_centre_nm(t_us, column_offset_us))


def sweep_times_us(rig: Rig) -> Float[Array, " t"]:
    """The simulator's time grid over one sweep: `samples_per_sweep + 1` points in µs."""
    n = rig.samples_per_sweep
    return jnp.arange(n + 1, dtype=rig.fwhm_nm.dtype) * (rig.period_us / n)
