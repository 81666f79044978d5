"""Calibration: fit the rig to captures of a chart of known reflectance.

**Residuals.** For every event of a chart pixel (known reflectance, used on the fine
grid), the sensor model (release mode, paper Eq. 2) says
$d_k = \\log(I(τ_k) + ε) - \\log(I(ρ_k) + ε) = σ_k C_{σ_k}$, $ρ_k = τ_{k-1} + η$ (the
recording start for the first event; each sweep's first event after that refers
across the dark part between sweeps and is left out, :func:`._chart.sweep_first_events`).
The residual is $r_k = d_k / C - σ_k$, in units of
the threshold (see :func:`chart_residuals` for why not log units): the forward model's
own equations at the *observed* event times — smooth in every parameter, finite
everywhere ($I + ε \\ge c + ε > 0$), and with no reconstruction inside. They are
fitted jointly with optimistix's Levenberg–Marquardt for the ON/OFF thresholds, the
sweep coefficient β, the constant light c, a smooth correction of D(λ), the band
profile, the photoreceptor's cut-off and one time offset τx per column (with a
second-difference smoothness prior across columns). The event residuals are never
linearised all at once: their Gauss–Newton normal equations are accumulated over
blocks of pixels and the solver sees a reduced residual with the same model
(:func:`_fit_residuals_scaled`), so memory is bounded by a block and a 1280-column
sensor (≈1300 unknowns) needs a 1300² matrix, not a dense Jacobian over its events.

**What gray patches can and cannot separate.**

- ON/OFF thresholds and c: separable — patches of different known reflectance see the
  same light at different levels, and the number and spacing of events depend on
  $\\log(R F(t)/c + 1)/C$ differently for different R.
- β and τx: separable from each other because the band's entry into and exit from the
  channel range (the sharp rise at 400 nm and fall at 760 nm) are two time anchors per
  column, 360 nm / (βω) apart.
- The photoreceptor's cut-off: separable from τx because the low-pass lags a pixel
  by about $1/(2π f_c I)$ — longer on a darker patch, while τx shifts every pixel of
  a column alike — and it also flattens the trace's shape near its peak. Fitted
  with the rest (`fit_photoreceptor`): a user rarely knows it (it depends on the
  sensor's biases), and a reconstruction that assumes an ideal photoreceptor on a
  10 kHz one lost ~10 dB (README, "Real sensors").
- λ0 (`sweep_start_nm`) is *not* separable from τx (λc depends on λ0 + βωτx only); it is
  kept fixed and τx absorbs it.
- β against an unknown camera response D(λ): a flat gray patch only sees D·E blurred by
  the band, so a mis-scaled β is equivalent to a stretched D except at the range edges.
  With the edges as anchors β is fixed here; on a rig without band-limiting filters a
  target of known spectral structure (a narrow-band filter or laser line at a known
  wavelength, or a white reference with a spectrometer reading) is needed.
- D(λ): a flat gray patch sees D·E through the *shape* of its intensity trace (the
  band blurs it), so a wrong D biases everything else; a smooth correction of D (a few
  Legendre terms of log D, `response_degree`) is therefore fitted jointly. Its overall
  scale is not identifiable (the peak normalisation removes it), and structure finer
  than the band is not seen: per-channel factors come from a white reference of known
  spectrum (:func:`spectral_correction`, paper supplement 6.1).
- The band profile: inside the channel range a flat patch sees the band only
  through its convolution with D·E, but where the band enters and leaves the range
  a pixel's intensity is the profile's cumulative integral (from c to the full
  level: ~20 crossings of a 0.15 threshold), and D is a smooth correction: so its
  shape is fitted (`fit_band`, the last stage). Its scale (the table's
  normalisation removes it) and a common shift (τx's) are not seen: a weak prior
  and a pinned centroid fix them.
- Per-pixel thresholds: with the global parameters fixed, each pixel's residuals are
  linear in its own C_on, C_off: closed-form means of the observed log steps
  (:func:`threshold_maps_from_chart`). Needs ≥ 1 ON and ≥ 1 OFF event per pixel; pixels
  without get the global value.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._base import call_exported, prepare_exported, release_free_memory
from .._model import (
    BandTable,
    Calibration,
    EventStream,
    Rig,
    Scene,
    band_overlap,
    fwhm_to_sigma,
    lookup,
    sampled_profile_product,
)
from .._reconstruct import lit_interval_us, noise_model, screen_events
from ._chart import (
    PHOTORECEPTOR_REF_HZ,
    ChartData,
    ChartSpeeds,
    PackedEvents,
    _closed_form_thresholds,
    _log_steps,
    _with_column_offsets,
    chart_data,
    chart_sweep_speeds,
    lowpassed_traces,
    packed_log_step_tangents,
    packed_log_steps,
    packed_scaled,
    packed_scaled_tangents,
    spectral_traces,
    sweep_first_events,
    threshold_maps_from_chart,
    with_reference_cutoff,
    without_band_profile,
)

__all__ = [
    "CalibrationResult",
    "calibrate",
    "spectral_correction",
    "apply_spectral_correction",
    "save_calibration",
]

TAU_SCALE_US = 100.0  # τx parameter unit in the solver
#: Levenberg–Marquardt's (rtol, atol) in a stage that another follows (the first, one
#: threshold pair, when per-pixel thresholds are profiled out after it) and in the
#: last stage (the only one with `per_pixel=False`), in the Jacobi-scaled variables
#: (unit diagonal of the Gauss–Newton matrix, so a parameter's statistical
#: uncertainty is about the RMS residual, ~2e-3 on a clean chart). Both stopping
#: tests (the step in the variables, the change of the reduced residuals) are
#: relative to those scales.
#: Until 2026-11-27 both stages used (1e-7, 1e-9): 38 steps on the 1280-column
#: benchmark chart, the last ~15 of them changing no parameter by more than 4e-9
#: relative (most rejected while the trust region shrank to meet the tests); the
#: first stage is only a start for the second. These tolerances take 24 steps there
#: (25–28 instead of 46 on the `realistic` chart, with the blocks below of 8,192 and
#: 4,096 events) and move every fitted value by < 1e-8 relative and τx by < 3e-8 µs
#: (experiments/PERFORMANCE_LOG.md, "Stopping tests").
LM_TOL = ((1e-4, 1e-5), (1e-5, 1e-6))
CURV_SCALE_NM = 1.0  # sweep-curvature parameter unit in the solver
SMOOTH_WEIGHT = 0.02  # residual weight of one µs of τx second difference
PHOTORECEPTOR_START_HZ = 10000.0  # the cut-off's start when the initial rig has none
PHOTORECEPTOR_SLOW_START_HZ = 2000.0  # the second start, when the first did not converge
PR_FLOOR = 1e-9  # (see _cutoff)
#: A fitted cut-off above this (Hz) counts as no low-pass (the ideal sensor's model
#: is used from then on): its time constant at a white pixel is < 0.32 µs, and the
#: lag at 5 % of white < 7 µs. Photoreceptors of event sensors reach a few kHz to
#: tens of kHz (README, "Real sensors"); an ideal sensor's chart fitted 2.7 MHz.
PHOTORECEPTOR_IDEAL_HZ = 500_000.0
#: The band profile's fit (`fit_band`): a smooth correction of log T over the
#: profile's offsets, piecewise linear between `BAND_KNOTS` knots spread over
#: ±`BAND_SPAN_FWHM` FWHM (constant beyond), multiplying the initial profile (a
#: Gaussian of `fwhm_nm`, or `init`'s `band_profile`). The profile is sampled on
#: ±3 FWHM (`BAND_SAMPLES` points), as `skewed_band_profile` samples it. (An
#: additive correction of T instead was tried: its floor at 0 left flat
#: directions in the tails, and the fit crept along them for 100+ steps.)
BAND_KNOTS = 17
BAND_SPAN_FWHM = 2.0
BAND_SAMPLES = 161
BAND_FLOOR = 1e-12  # the initial profile's floor (of its peak) under the correction
#: A chart wider than `BAND_DIRECT_COLUMNS` has its band fitted on its middle
#: `BAND_CROP_COLUMNS` columns first (a whole calibration of that strip); the whole
#: chart is then fitted with that band kept and the strip's other global values as
#: its start. Over all columns the band's fit needs many more steps: a 48x1280
#: chart's profiled stage took 81 (2026-11-28, with the band's traces by
#: convolution and the noise-aware trust region; it had not converged in 60 before),
#: 98 steps in all against the strip path's 22 (319 s in a development run on a
#: loaded machine, verbose, against ~50 s). A 64-column strip took
#: 68.5 / 43.5 s against the 32-column one's 61.8 / 34.6 s (first / second process,
#: experiments/PERFORMANCE_LOG.md, "The band profile").
BAND_DIRECT_COLUMNS = 64
BAND_CROP_COLUMNS = 32
BAND_SMOOTH_WEIGHT = 1.0
BAND_RIDGE_WEIGHT = 0.01
BAND_SHIFT_WEIGHT = 1.0  # per nm of the centroid's move


# --- the joint fit ---------------------------------------------------------------------
def _normal_cg(rtol, atol):
    """CG on the normal equations (matrix-free): `lx.Normal(lx.CG)` in newer lineax,
    `lx.NormalCG` before it."""
    if hasattr(lx, "Normal"):
        return lx.Normal(lx.CG(rtol=rtol, atol=atol))
    return lx.NormalCG(rtol=rtol, atol=atol)


def _response_basis(rig: Rig, degree: int) -> np.ndarray:
    """Legendre polynomials P1..P_degree over the channel range, on the fine grid
    (`(degree, F)`): the smooth log-correction of D(λ) a gray chart can identify (P0 is
    the overall scale, which the peak normalisation removes)."""
    g = rig.grid
    u = 2.0 * (g.fine_centres_nm - g.start_nm) / (g.stop_nm - g.start_nm) - 1.0
    rows = [np.polynomial.legendre.Legendre.basis(j)(u) for j in range(1, degree + 1)]
    return np.stack(rows) if rows else np.zeros((0, u.shape[0]))  # 0: D kept


#: Events per block of the fit's passes (:class:`._chart.PackedEvents`). 2^12 since
#: 2026-11-27: the warm in-process calibration of the 1280-column benchmark chart took
#: 25.0 / 23.7 s against 27.8 / 28.2 s with 2^13 and 41.7 s with 2^15 (two runs each,
#: same steps and fitted rig; 2^10 took 26.8 s and two more steps): each block's
#: G + 1 tangents of its intermediates stay in the cache. (Those blocks were padded
#: per pixel to a power of two; packed, a block holds ~1.3× the events.)
BLOCK_EVENTS = 1 << 12
#: Up to this many blocks their count is a power of two (`_blocks_of`): a new capture
#: of the same small chart then has the same shapes, and reuses the compiled
#: programs instead of spending ~10 s compiling its own.
SMALL_BLOCKS = 16
#: Each pixel's events start at a multiple of this many slots in a block, so that the
#: normal equations' per-column sums add every `COLUMN_CHUNK` slots first (one column
#: each) and scatter E / `COLUMN_CHUNK` rows instead of E: XLA's CPU scatter runs on
#: one thread, and per event it was ~10 % of a 16×512 chart's pass.
COLUMN_CHUNK = 4


class _FitData(eqx.Module):
    """What the chart-fit residuals read besides the parameters (all arguments, no
    closures: see `_fit_chart_float64`).

    The chart's events travel in blocks (`blocks`, a :class:`._chart.PackedEvents`
    of `(n_blocks, BLOCK_EVENTS)` fields): each pixel's events one after another, as
    many pixels as fit in a block. Every pass over them holds one block's
    intermediates at a time, so the fit's memory is bounded by the block, not by the
    sensor's width; and one block program serves pixels of every event count. (Until
    2026-12-07 the pixels were sorted into buckets of event counts padded to powers of
    two, one traced pass per bucket in every program: a 12×16 chart's solver, three
    buckets, took ~11-13 s to compile, ~8.5 s with one.) The fit's programs' per-event
    inputs and outputs (`keep`, the residuals) have the blocks' shape (`_Layout` maps
    them to the chart's lists): the programs depend on the number of blocks alone, so
    a new capture of the same chart runs the programs compiled for the last one.
    """

    rig: Rig
    basis: Any
    blocks: Any
    spectra: Any
    fixed_traces: Any
    overlap: Any  # the band's overlap table (computed once when the band is not fitted)
    band: Any  # fitted band: (sample offsets, log of the initial profile, knots), or None
    band_gate: Any  # 1: the band correction acts; 0: not (the first stage)
    overlap_lo_nm: float = eqx.field(static=True)
    overlap_step_nm: float = eqx.field(static=True)
    fit_baseline: bool = eqx.field(static=True)


def _fit_data(rig, basis, blocks, spectra, fixed_traces, overlap, band, gate,
              fit_baseline) -> _FitData:  # fmt: skip
    """The fit's :class:`_FitData` (`overlap`: the rig's :func:`band_overlap`). Its
    rig has no band profile: the band enters through `overlap` or `band`, and the
    profile, a static value, would put its values into every program's key (see
    :func:`without_band_profile`)."""
    return _FitData(without_band_profile(rig), basis, blocks, jnp.asarray(spectra),
                    fixed_traces, overlap.values, band, gate, overlap.lo_nm,
                    overlap.step_nm, fit_baseline)  # fmt: skip


def _blocks_of(need: int) -> int:
    """`need` blocks rounded up to few values, so that captures of one chart share
    their programs: a power of two up to `SMALL_BLOCKS` (that few cost milliseconds
    per pass), else a multiple of 1/16 of the power of two below (at most 1/16 more:
    903 blocks become 912)."""
    need = max(1, need)
    if need <= SMALL_BLOCKS:
        return 1 << (need - 1).bit_length()
    step = (1 << (need.bit_length() - 1)) // 16
    return -(-need // step) * step


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where the chart's event lists (`(n, k)`, :class:`ChartData`) sit in the packed
    blocks (`shape`, `(n_blocks, E)`): list entry `(rows[i], pos[i])` is flat slot
    `slot[i]`; `column`: each slot's sensor column (padding: 0)."""

    shape: tuple[int, int]
    rows: np.ndarray
    pos: np.ndarray
    slot: np.ndarray
    column: np.ndarray
    lists: tuple[int, int]

    def per_slot(self, values, dtype):
        """Per-pixel `values` at each of its slots, `(n_blocks, E)` (padding: 0)."""
        out = np.zeros(self.shape[0] * self.shape[1], dtype)
        out[self.slot] = np.asarray(values)[self.rows]
        return jnp.asarray(out.reshape(self.shape))

    def to_lists(self, values) -> np.ndarray:
        """Per-slot `values` (`(n_blocks, E)`) → the chart's lists, `(n, k)` (0 where
        a list has no slot: past a pixel's last event)."""
        flat = np.asarray(values).reshape(-1)
        out = np.zeros(self.lists, flat.dtype)
        out[self.rows, self.pos] = flat[self.slot]
        return out


def _packed(data: ChartData, dtype):
    """The chart's event lists packed into blocks (:class:`._chart.PackedEvents`,
    fields `(n_blocks, E)`, device arrays) and their :class:`_Layout`.

    Each pixel's slots up to its last event (a slot in between that the chart's
    screening dropped stays, masked, so every event's reference is the slot before
    it, as in the lists), the pixels in their order, a pixel that does not fit in
    what is left of a block starting the next one, each at a multiple of
    `COLUMN_CHUNK` slots. E is `BLOCK_EVENTS`, or the longest pixel's slots rounded up
    to a power of two."""
    mask = np.asarray(data.mask)
    n, k = mask.shape
    length = np.where(mask.any(axis=1), k - np.argmax(mask[:, ::-1], axis=1), 0)
    e = max(BLOCK_EVENTS, 1 << int(max(int(length.max(initial=1)) - 1, 0)).bit_length())
    start = np.zeros(n, np.int64)  # each pixel's first slot
    local = np.zeros(n, np.int64)  # its index in its block
    offset, in_block = 0, 0
    c = COLUMN_CHUNK
    for i, m in enumerate(length.tolist()):
        offset = -(-offset // c) * c
        if offset % e + m > e or (in_block and offset % e == 0):  # the next block
            offset, in_block = -(-offset // e) * e, 0
        start[i], local[i] = offset, in_block
        offset += m
        in_block += 1
    shape = (_blocks_of(-(-offset // e)), e)
    rows = np.repeat(np.arange(n), length)
    pos = np.arange(rows.size) - np.repeat(np.cumsum(length) - length, length)
    slot = start[rows] + pos
    t = np.asarray(data.t_us, dtype)
    size = shape[0] * e
    column = np.zeros(size, np.asarray(data.column).dtype)  # (padding: 0)
    column[slot] = np.asarray(data.column)[rows]

    def field(values, fill, kind):
        out = np.full(size, fill, kind)
        out[slot] = values
        return jnp.asarray(out.reshape(shape))

    # A slot that no event fills (masked) belongs to the pixel before it, keeping the
    # indices sorted along the block.
    pixel = np.full(size, -1, np.int32)
    pixel[slot] = local[rows]
    pixel = np.maximum(np.maximum.accumulate(pixel.reshape(shape), axis=1), 0)
    blocks = PackedEvents(
        t=field(t[rows, pos], 0, dtype),
        first=field(pos == 0, True, bool),
        polarity=field(np.asarray(data.polarity)[rows, pos], 0, np.int32),
        mask=field(mask[rows, pos], False, bool),
        column=jnp.asarray(column.reshape(shape)),
        spectrum=field(np.asarray(data.spectrum)[rows], 0, np.asarray(data.spectrum).dtype),
        pixel=jnp.asarray(pixel),
    )
    layout = _Layout(shape, rows, pos, slot, column.reshape(shape), (n, k))
    return blocks, layout


def _fit_rig(params, fit: _FitData) -> Rig:
    r = _apply(params, fit.rig, fit.basis)
    if not fit.fit_baseline:
        r = r.with_leaves(baseline_rel=fit.rig.baseline_rel)
    return r


def _fit_tables(params, fit: _FitData):
    """The chart spectra's intensity traces over λc (and their photoreceptor-filtered
    log levels when the rig has a low-pass; else an empty array) at `params`: computed
    once per evaluation and shared by every block."""
    r = _fit_rig(params, fit)
    overlap = BandTable(fit.overlap, fit.overlap_lo_nm, fit.overlap_step_nm)
    product = None
    if "band" in params:
        # The traces are the band's overlap table times the weighted spectra: formed
        # without the table (its tangent along each band parameter was most of a
        # step's cost on a strip; see sampled_profile_product).
        theta = params["band"] * fit.band_gate

        def product(weights):
            return sampled_profile_product(
                fit.band[0], _band_values(theta, fit.band), r.grid.fine_edges_nm,
                fit.overlap_lo_nm, fit.overlap_step_nm, fit.overlap.shape[0], weights,
            )  # fmt: skip

    traces = (
        BandTable(fit.fixed_traces, fit.overlap_lo_nm, fit.overlap_step_nm)
        if fit.fixed_traces is not None
        else spectral_traces(r, fit.spectra, overlap, product)
    )
    if "pr" in params or r.effects.photoreceptor_hz > 0:
        # (a fitted cut-off: the rig's static one is the reference)
        hz = _cutoff(params) if "pr" in params else None
        return traces.values, lowpassed_traces(r, traces, hz).values
    return traces.values, jnp.zeros((0,), traces.values.dtype)


def _block_log_steps(rig: Rig, tables, block, fit: _FitData):
    """The model log steps of one packed block's events, `(E,)` (`rig`: the fit's,
    :func:`_fit_rig`)."""
    lo, step = fit.overlap_lo_nm, fit.overlap_step_nm
    traces = BandTable(tables[0], lo, step)
    filtered = BandTable(tables[1], lo, step) if tables[1].size else None
    return packed_log_steps(rig, block, traces, filtered)


def _block_residuals(params, tables, block, keep, profile, fit: _FitData):
    """Event residuals of one packed block, `(E,)` (0 in padding and in dropped
    pixels)."""
    r = _fit_rig(params, fit)
    d = _block_log_steps(r, tables, block, fit)
    return packed_scaled(r, block, d, profile) * keep


def _band_values(theta, band):
    """The band profile's samples at its offsets for the correction `theta` (log
    units at the knots, constant beyond the outer ones): the initial profile times
    exp(piecewise-linear θ)."""
    offsets, log0, knots = band
    return jnp.exp(log0 + jnp.interp(offsets, knots, theta))


def _band_start(rig: Rig, dtype):
    """`(offsets, log of the initial profile, knots)` of the band's fit (arrays):
    the initial profile is `rig`'s sampled profile or its Gaussian, floored at
    `BAND_FLOOR` of its peak so that the correction can raise a tail."""
    fwhm = float(rig.fwhm_nm)
    offsets = np.linspace(-3.0 * fwhm, 3.0 * fwhm, BAND_SAMPLES)
    if rig.band_profile is None:
        t0 = np.exp(-0.5 * (offsets / fwhm_to_sigma(fwhm)) ** 2)
    else:
        off, val = (np.asarray(v, np.float64) for v in rig.band_profile)
        t0 = np.interp(offsets, off, val, left=0.0, right=0.0)
    t0 = np.maximum(t0 / t0.max(), BAND_FLOOR)
    knots = np.linspace(-BAND_SPAN_FWHM * fwhm, BAND_SPAN_FWHM * fwhm, BAND_KNOTS)
    return tuple(jnp.asarray(a, dtype) for a in (offsets, np.log(t0), knots))


def _band_prior(theta, band):
    """The band correction's prior residuals: weighted second differences between
    knots (smoothness), weighted values (a weak pull to the start) and the weighted
    move of the profile's centroid from the initial one's (nm). A common shift of
    the band is not seen by the events — τx absorbs it — so it is pinned here and
    the two do not trade."""
    d2 = theta[2:] - 2.0 * theta[1:-1] + theta[:-2]
    offsets, t0 = band[0], jnp.exp(band[1])
    t = _band_values(theta, band)
    move = jnp.sum(offsets * t) / jnp.sum(t) - jnp.sum(offsets * t0) / jnp.sum(t0)
    return jnp.concatenate(
        [
            BAND_SMOOTH_WEIGHT * d2,
            BAND_RIDGE_WEIGHT * theta,
            (BAND_SHIFT_WEIGHT * move)[None],
        ]
    )


def fitted_band_profile(theta, band) -> dict:
    """The fitted band as the rig key `band_profile` (peak 1)."""
    vals = np.asarray(_band_values(jnp.asarray(theta), band), np.float64)
    return {
        "offset_nm": [float(v) for v in np.asarray(band[0])],
        "values": [float(v) for v in vals / vals.max()],
    }


def _prior_residuals(params, fit: _FitData):
    """The τx smoothness prior: second differences of the absolute column offsets
    (the starting guess may be rough), weighted."""
    tau = fit.rig.column_offsets_us + TAU_SCALE_US * params["tau"]
    return SMOOTH_WEIGHT * (tau[2:] - 2 * tau[1:-1] + tau[:-2])


@eqx.filter_jit
def _fit_residuals(params, profile, keep, fit: _FitData):
    """Event residuals of every slot of the packed blocks (see :class:`_FitData`),
    `(n_blocks, E)`, block by block (padding: zeros)."""
    tables = _fit_tables(params, fit)

    def one(xs):
        block, kb = xs
        return _block_residuals(params, tables, block, kb, profile, fit)

    return jax.lax.map(one, (fit.blocks, keep))


def _cutoff(params):
    """The photoreceptor cut-off (Hz) of the fit's parameter `pr`: the filter's time
    constant at a white pixel is `pr` times the reference one
    (`PHOTORECEPTOR_REF_HZ`), and `pr ≤ 0` is the ideal sensor (no low-pass: the
    residuals are flat there, and the parameter's column of the Jacobian is zero).
    So an ideal sensor is a point the fit reaches: with the cut-off itself (or its
    logarithm) as the parameter, a fit of an ideal sensor walked towards an
    infinite cut-off with ever smaller gains and did not converge."""
    return PHOTORECEPTOR_REF_HZ / jnp.maximum(params["pr"], PR_FLOOR)


def _unscale(u, scale):
    """Solver variables u = θ·s → parameters θ."""
    return jax.tree.map(lambda a, b: a / b, u, scale)


def _theta(u_flat, unravel, scale):
    return _unscale(unravel(u_flat), scale)


def _table_tangents(u_flat, unravel, scale, fit: _FitData, tans, band_size: int):
    """The tables (:func:`_fit_tables`) at `u_flat` and their tangents along each row
    of `tans`: `(tables, d_tables)`.

    With the band fitted (its `band_size` parameters first in `u_flat`, and the unit
    tangents of `tans`' first rows), the traces are a product bilinear in the band's
    cumulative profile and the weighted spectra (`sampled_profile_product`): a band
    tangent moves only the first factor and every other tangent only the second. So
    the two groups are linearised apart, each product's tangent is one convolution
    instead of two. The tangents are taken one after another (`lax.map`): XLA's CPU
    backend ran the batched (`vmap`) tangents of the table's gathers, interpolations
    and convolutions 2.5–3.5× slower than one at a time. On a 16×24, 8-sweep chart
    with the band fitted (2026-12-07, float64, 2 cores): the tables' 27 tangents
    took 168 ms batched in one linearisation, 67 ms now."""

    def tables(uf):
        return _fit_tables(_theta(uf, unravel, scale), fit)

    if band_size == 0:
        primal, lin = jax.linearize(tables, u_flat)
        return primal, jax.lax.map(lin, tans)
    head, tail = u_flat[:band_size], u_flat[band_size:]
    primal, lin_b = jax.linearize(lambda b: tables(jnp.concatenate([b, tail])), head)
    _, lin_r = jax.linearize(lambda r: tables(jnp.concatenate([head, r])), tail)
    d_b = jax.lax.map(lin_b, tans[:band_size, :band_size])
    d_r = jax.lax.map(lin_r, tans[band_size:, band_size:])
    return primal, jax.tree.map(lambda a, b: jnp.concatenate([a, b]), d_b, d_r)


def _normal_equations(
    u_flat, unravel, scale, profile, keep, fit: _FitData, tau_idx, band_size: int = 0
):
    """Gauss–Newton normal equations of the event residuals at `u_flat` (scaled,
    flattened parameters), accumulated over blocks of pixels: the blocks of JᵀJ
    (global × global, τx × global, the τx diagonal), of Jᵀr (global, τx) and rᵀr.

    Each residual depends on the few global parameters and on its own column's τx
    only, so a block's Jacobian is `G + 1` forward-mode products: one per global
    parameter and one with every τx moved at once (each residual sees only its own).
    The tables the events read and the column offsets are linearised once per
    evaluation (:func:`_table_tangents`); each block then reads them with all their
    tangents at once (:func:`._chart.packed_log_step_tangents`). Until 2026-12-08
    each block was linearised and its tangents taken one after another (`lax.map`),
    each reading the tables again: a 48×1280 chart's system took 1.5-1.9 s, now
    0.65-1.0 s (2 cores). The τx part of JᵀJ is then diagonal and the τx–global part
    one segment sum per block (over the events' columns); nothing larger than a
    block's residuals and their tangents is ever held.
    """
    p = u_flat.shape[0]
    w = tau_idx.size
    g = p - w  # the globals come first in the flattened parameters (_tau_positions)
    tans = jnp.zeros((g + 1, p), u_flat.dtype)
    tans = tans.at[np.arange(g), np.arange(g)].set(1.0).at[g, tau_idx].set(1.0)
    tables, d_tables = _table_tangents(u_flat, unravel, scale, fit, tans, band_size)
    dtype = u_flat.dtype

    def inverse_thresholds(uf):
        r = _fit_rig(_theta(uf, unravel, scale), fit)
        return jnp.stack([1.0 / r.threshold_on, 1.0 / r.threshold_off])

    inv, inv_lin = jax.linearize(inverse_thresholds, u_flat)
    d_inv = jax.vmap(inv_lin)(tans)  # (G + 1, 2)

    def rig_at(uf):
        return _fit_rig(_theta(uf, unravel, scale), fit)

    def with_tangents(value, tangents):  # a trailing axis: the value, its tangents
        return jnp.concatenate([value[..., None], jnp.moveaxis(tangents, 0, -1)], -1)

    # What every block reads, with its tangents: the table the events see (the
    # low-passed traces when the rig has a cut-off: the test `_log_steps_at` and
    # `packed_log_step_tangents` make) and the column offsets.
    which = int(rig_at(u_flat).effects.photoreceptor_hz > 0)
    traces = BandTable(
        with_tangents(tables[which], d_tables[which]),
        fit.overlap_lo_nm,
        fit.overlap_step_nm,
    )
    offsets, off_lin = jax.linearize(lambda uf: rig_at(uf).column_offsets(w), u_flat)
    offsets = with_tangents(offsets, jax.vmap(off_lin)(tans))

    def log_steps(block):  # and their tangents, (E,) and (G + 1, E)
        return packed_log_step_tangents(rig_at, u_flat, tans, block, traces, offsets)

    def no_events(block):  # a padding block (`_blocks_of`)
        return jnp.zeros_like(block.t), jnp.zeros(tans.shape[:1] + block.t.shape, dtype)

    def body(carry, xs):
        block, kb = xs
        # The log steps' tangents, then the residuals', all at once. Behind a `cond`:
        # the padding blocks skip the work, and the branch's outputs are arrays in
        # memory. XLA's CPU compiler otherwise fused the tangents' interpolation
        # into each of the per-pixel sums' consumers (no `optimization_barrier`
        # survives its pipeline), computing it again for each: 2.6 s instead of
        # 0.63 s per pass over a 48×1280 chart (2026-12-08).
        d, jd = jax.lax.cond(block.mask.any(), log_steps, no_events, block)
        r, jac = packed_scaled_tangents(block, d, jd, inv, d_inv, profile)
        r, jac = r * kb, jac * kb
        jg, jt = jac[:g], jac[g]
        # The τx sums per column, in one segment sum: (W, G + 2), each chunk of
        # slots (one pixel's: `_packed`) added first.
        rows = jnp.concatenate([jg * jt, (jt * jt)[None], (jt * r)[None]])
        c = COLUMN_CHUNK
        rows = rows.reshape(rows.shape[0], -1, c).sum(-1)
        cols = jax.ops.segment_sum(rows.T, block.column[::c], num_segments=w)
        hgg, hgt, htt, bg, bt, ss = carry
        return (
            hgg + jg @ jg.T,
            hgt + cols[:, :g],
            htt + cols[:, g],
            bg + jg @ r,
            bt + cols[:, g + 1],
            ss + r @ r,
        ), None

    carry = (  # the sums start at zero
        jnp.zeros((g, g), dtype),
        jnp.zeros((w, g), dtype),
        jnp.zeros((w,), dtype),
        jnp.zeros((g,), dtype),
        jnp.zeros((w,), dtype),
        jnp.zeros((), dtype),
    )
    carry, _ = jax.lax.scan(body, carry, (fit.blocks, keep))
    return carry


def _tau_positions(u) -> np.ndarray:
    """Positions of the τx entries in the flattened parameters: the last ones (dict
    keys flatten sorted, and "tau" sorts last — the normal equations are assembled as
    [globals, τx] blocks)."""
    if sorted(u)[-1] != "tau":
        raise AssertionError("the τx parameters must flatten last")
    total = sum(int(np.size(v)) for v in u.values())
    return np.arange(total - int(np.size(u["tau"])), total)


def _events_system(u, args):
    """Normal equations of the event residuals alone (no prior) at scaled parameters
    `u`, as the blocks of :func:`_normal_equations`."""
    scale, (profile, keep, fit) = args
    u_flat, unravel = jax.flatten_util.ravel_pytree(u)
    band_size = int(np.size(u["band"])) if "band" in u else 0
    return _normal_equations(
        u_flat, unravel, scale, profile, keep, fit, _tau_positions(u), band_size
    )


def _fit_system(u, args):
    """The fit's full normal equations (events and τx prior) at scaled parameters
    `u`: `(JᵀJ, Jᵀr, rᵀr)` in the flattened variables."""
    scale, (_, _, fit) = args
    hgg, hgt, htt, bg, bt, ss = _events_system(u, args)
    w = htt.shape[0]
    # The prior is linear in τx: row i of its Jacobian has three entries (columns i,
    # i+1, i+2), so its share of JᵀJ is pentadiagonal and added by diagonals.
    rp = _prior_residuals(_unscale(u, scale), fit)
    c = SMOOTH_WEIGHT * TAU_SCALE_US / scale["tau"]  # d(τx)/d(u) times the weight
    n = w - 2  # prior rows (none for a sensor under three columns)
    htt = jnp.diag(htt)
    if n > 0:
        bands = (c[:n], -2.0 * c[1 : n + 1], c[2 : n + 2])  # the entries of row i
        bt = bt + sum(jnp.pad(v * rp, (q, 2 - q)) for q, v in enumerate(bands))
        for off in range(3):  # diagonal `off` of the prior's Gram matrix
            d = sum(
                jnp.pad(bands[q] * bands[q + off], (q, 2 - q)) for q in range(3 - off)
            )[: w - off]
            htt = htt + jnp.diag(d, off) + (jnp.diag(d, -off) if off else 0.0)
    if "band" in u:
        # The band correction's prior; "band" flattens first, so its entries are the
        # first of the globals.
        k = u["band"].shape[0]

        def prior(ub):
            return _band_prior(ub / scale["band"], fit.band)

        rb = prior(u["band"])
        jb = jax.jacfwd(prior)(u["band"])
        hgg = hgg.at[:k, :k].add(jb.T @ jb)
        bg = bg.at[:k].add(jb.T @ rb)
        ss = ss + rb @ rb
    h = jnp.block([[hgg, hgt.T], [hgt, htt]])
    return h, jnp.concatenate([bg, bt]), ss + rp @ rp


def _reduced(h, b, ss):
    """A residual vector of length P + 1 and its Jacobian `(Lᵀ; 0)` (H = LLᵀ) with the
    same Gauss–Newton model as the full residuals: JᵀJ = H, Jᵀr = b, ‖r‖² = ss."""
    d = jnp.diag(h)
    # Parameters the residuals do not depend on (profiled-out thresholds, c when it is
    # not fitted): a unit pivot keeps the factorisation defined; their gradient is 0.
    h = h + jnp.diag(jnp.where(d > 0, 1e-12 * jnp.max(d), 1.0))
    lower = jnp.linalg.cholesky(h)
    z = jax.scipy.linalg.solve_triangular(lower, b, lower=True)
    rest = jnp.sqrt(jnp.maximum(ss - z @ z, 0.0))
    return jnp.concatenate([z, rest[None]]), lower


def _fit_residuals_scaled(u, args):
    """What optimistix's Levenberg–Marquardt sees, in the scaled variables u = θ·s.

    Not the ~10⁵–10⁶ event residuals themselves: their Gauss–Newton model reduced to
    P + 1 numbers (P parameters). With $J^TJ = H = LL^T$, $b = J^Tr$, the vector
    $\\tilde r = (L^{-1}b,\\ \\sqrt{\\|r\\|^2 - \\|L^{-1}b\\|^2})$ with Jacobian
    $\\tilde J = (L^T; 0)$ has $\\tilde J^T\\tilde J = H$, $\\tilde J^T\\tilde r = b$
    and $\\|\\tilde r\\| = \\|r\\|$: every quantity the solver uses (the damped
    Gauss–Newton step, the actual and predicted reductions, the stopping tests) is the
    full problem's. Its memory is that of one block of pixels plus P² (the events are
    never linearised at once), and each conjugate-gradient iteration of a step is a
    P × P product instead of a pass over all the events.
    """
    u_flat, unravel = jax.flatten_util.ravel_pytree(u)
    # The rule is traced lazily (when the solver linearises), so the arrays it reads
    # are arguments, not closed over; only static values are closed over.
    dynamic, static = eqx.partition(args, eqx.is_array)

    @jax.custom_jvp
    def reduced(uf, dyn):
        return _reduced(*_fit_system(unravel(uf), eqx.combine(dyn, static)))[0]

    @reduced.defjvp
    def reduced_jvp(primals, tangents):
        (uf, dyn), (tf, _) = primals, tangents
        r, lower = _reduced(*_fit_system(unravel(uf), eqx.combine(dyn, static)))
        return r, jnp.concatenate([lower.T @ tf, jnp.zeros((1,), tf.dtype)])

    return reduced(u_flat, dynamic)


def _apply(params, base: Rig, basis=None) -> Rig:
    """Solver parameters (normalised) → rig."""
    if basis is not None and basis.shape[0]:
        resp = base.camera_response * jnp.exp(
            params["resp"] @ jnp.asarray(basis, base.fwhm_nm.dtype)
        )
        base = base.with_leaves(camera_response=resp / jnp.max(resp))
    extra = {}
    if "curv" in params:
        extra["sweep_curvature_nm"] = (
            base.sweep_curvature_nm + CURV_SCALE_NM * params["curv"]
        )
    return base.with_leaves(
        threshold_on=base.threshold_on * jnp.exp(params["log_on"]),
        threshold_off=base.threshold_off * jnp.exp(params["log_off"]),
        beta_nm_per_rad=base.beta_nm_per_rad * jnp.exp(params["log_beta"]),
        baseline_rel=base.baseline_rel * jnp.exp(params["log_c"]),
        column_offsets_us=base.column_offsets_us + TAU_SCALE_US * params["tau"],
        **extra,
    )


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """A fitted rig and how the fit went."""

    rig: Rig
    threshold_on_map: np.ndarray | None
    threshold_off_map: np.ndarray | None
    hot_pixels: np.ndarray | None
    converged: bool  # Levenberg–Marquardt met its tolerances (else: max_steps)
    outlier_pixels: int  # chart pixels dropped for unexplained events
    rms_residual: float  # threshold units (1 = one threshold), over all fitted events
    rms_residual_initial: float
    steps: int
    events_used: int
    pixels_used: int
    seconds: float
    psf_sigma_px: float | None = None  # the chart's blur chosen for the maps
    photoreceptor_fitted: bool = False  # the cut-off measured (else kept from init)
    band_fitted: bool = False  # the band profile fitted (else kept from init)
    band_unresolved: bool = False  # its fit was tried and did not converge: kept
    # Each chart sweep's mirror speed as measured (None: not measured), and whether
    # the fit read the sweeps at them (their spread above the estimate's error).
    sweep_speeds: ChartSpeeds | None = None
    sweep_speeds_used: bool = False

    @property
    def calibration(self) -> Calibration:
        """The result as a :class:`Calibration` (what `reconstruct` takes)."""
        e = self.rig.effects
        return Calibration(
            self.rig,
            self.threshold_on_map,
            self.threshold_off_map,
            self.hot_pixels,
            {
                "rms_residual_thresholds": self.rms_residual,
                "rms_residual_initial": self.rms_residual_initial,
                "converged": self.converged,
                "steps": self.steps,
                "events_used": self.events_used,
                "pixels_used": self.pixels_used,
                "outlier_pixels": self.outlier_pixels,
                "hot_pixels": int(
                    0 if self.hot_pixels is None else self.hot_pixels.sum()
                ),
                "threshold_noise": float(e.threshold_noise),
                "timestamp_jitter_us": float(e.timestamp_jitter_us),
                "noise_rate_hz": float(self.rig.noise_rate_hz),
                "psf_sigma_px": self.psf_sigma_px,
                "seconds": self.seconds,
                "photoreceptor_hz": float(e.photoreceptor_hz),
                "photoreceptor": "fitted (0: none found)"
                if self.photoreceptor_fitted
                else "kept from the initial rig",
                "band": "profile fitted"
                if self.band_fitted
                else "kept from the initial rig"
                + (" (its fit did not converge)" if self.band_unresolved else ""),
                "sweep_rate_jitter": float(e.sweep_rate_jitter),
                "sweep_speed": self.sweep_speed_note,
                "chart_sweep_speeds": None
                if self.sweep_speeds is None
                else [round(float(f), 6) for f in self.sweep_speeds.factors],
            },
        )

    @property
    def sweep_speed_note(self) -> str:
        """How the fit read the chart's sweeps (the report's `sweep_speed`)."""
        sp = self.sweep_speeds
        if sp is None:
            return "not measured (one speed)"
        n, pct = int(sp.measured.sum()), 100.0 * sp.jitter
        if self.sweep_speeds_used:
            return f"each of {n} sweeps read at its own speed (spread {pct:.3f} %)"
        if sp.significant:
            return (f"one speed: the fit at the {n} sweeps' own speeds (spread "
                    f"{pct:.3f} %) failed")  # fmt: skip
        return f"one speed ({n} sweeps agree within the estimate's error)"


class NotConverged(ValueError):
    """A calibration's Levenberg–Marquardt stopped at its step limit."""


SCREEN_MARGIN_US = 500.0  # lit-interval margin when screening a chart capture
MAX_RMS_RESIDUAL = 0.5  # threshold units: above, the capture is not the chart


def _sweeps_of(events, rig, t_start_us) -> int:
    span = float(events.t_us[-1] - t_start_us) if len(events) else 0.0
    return max(1, int(np.ceil((span + 1.0) / float(rig.period_us))))


def _outlier_pixels(r: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Pixels with a residual beyond max(0.5, 8 robust σ) threshold units."""
    vals = np.abs(r[mask])
    if vals.size == 0:
        return np.zeros(r.shape[0], bool)
    sigma = 1.4826 * np.median(vals)
    limit = max(0.5, 8.0 * sigma)
    return np.any((np.abs(r) > limit) & mask, axis=1)


def measure_noise(rig: Rig, data: ChartData, residuals: np.ndarray) -> dict:
    """Per-crossing threshold noise and timestamp jitter from the fitted residuals.

    A residual $r_k$ (threshold units, each pixel's own thresholds profiled out) times
    C is the event's log-step error, whose variance is $σ_C^2 + 2σ_t^2 s_k^2$ plus
    the timestamps' rounding $2 s_k^2/12$ (the model of
    :func:`evhsi_jax.reconstruction.pixel_system`), $s_k$ the log-intensity's slope
    at the event — on a chart known from the model. The two are separable because
    the slope differs from event to event: least squares of $(r_k C)^2$ on
    $[1, 2 s_k^2]$, after dropping the top 1 % (outliers), each clipped at 0. (The
    photoreceptor's cut-off is a parameter of the fit itself, not measured here.)

    **Returns:** `{"threshold_noise": σ_C, "timestamp_jitter_us": σ_t}`.
    """
    c = 0.5 * (float(rig.threshold_on) + float(rig.threshold_off))
    steps = _log_steps(rig, data)
    t = data.t_us
    t_ref = np.concatenate(
        [np.zeros_like(t[:, :1]), t[:, :-1] + float(rig.refractory_us)], axis=1
    )  # noqa: E501
    slope = np.abs(steps) / np.maximum(t - t_ref, 1.0)
    m = data.mask & np.isfinite(residuals)
    m[:, 0] = False  # the first event refers to the recording start
    e2 = (residuals * c)[m] ** 2
    s2 = 2.0 * slope[m] ** 2
    if e2.size < 10:
        return {"threshold_noise": 0.0, "timestamp_jitter_us": 0.0}
    keep = e2 <= np.quantile(e2, 0.99)
    a = np.stack([np.ones(keep.sum()), s2[keep]], axis=1)
    coef, *_ = np.linalg.lstsq(a, e2[keep] - s2[keep] / 12.0, rcond=None)
    return {
        "threshold_noise": float(np.sqrt(max(coef[0], 0.0))),
        "timestamp_jitter_us": float(np.sqrt(max(coef[1], 0.0))),
    }


def _background_rate(events, hot, rig, t_start_us) -> float:
    """Background-activity rate per pixel (Hz): events outside the lit intervals of
    pixels that are not hot, over the dark time they had."""
    sweeps = _sweeps_of(events, rig, t_start_us)
    kept, _, _ = screen_events(events, rig, t_start_us, noise_model(rig), sweeps, hot)
    h, w = events.height, events.width
    n_out = len(events) - len(kept) - int(np.isin(
        events.y.astype(np.int64) * w + events.x, np.flatnonzero(hot)
    ).sum())  # fmt: skip
    offs = np.asarray(rig.column_offsets(w), np.float64)
    t_arrive, t_leave = (np.asarray(v, np.float64) for v in lit_interval_us(rig, offs))
    dark = float(np.mean(float(rig.period_us) - (t_leave - t_arrive) - 400.0)) * sweeps
    n_pix = max(h * w - int(hot.sum()), 1)
    return max(n_out, 0) / (n_pix * max(dark, 1.0) * 1e-6)


@eqx.filter_jit
def _model_crossings(rig: Rig, spectra):
    """The exact pixel model's events along λc for each chart spectrum at `rig`
    (:func:`initial_guess`): `(fired, λ of the crossing)`, each `(λ samples, S)`, on a
    0.25 nm grid over the band table's range. One compiled program (as eager
    operations, ~60 small compilations: ~2 s of a first run)."""
    from .._model import exact_events_scan

    traces = spectral_traces(rig, spectra)
    n_tab = traces.values.shape[0]
    dtype = traces.values.dtype
    lam = np.arange(traces.lo_nm, traces.lo_nm + traces.step_nm * (n_tab - 1), 0.25)
    lam = jnp.asarray(lam, dtype)
    a = lookup(traces, lam)
    log_i = jnp.log(jnp.maximum(a, 0.0) + rig.baseline_level)  # λ plays time's role
    eta_nm = rig.refractory_us * rig.beta_nm_per_rad * rig.omega_rad_per_us
    s = spectra.shape[0]
    (fired, tc, _), _ = exact_events_scan(
        log_i, lam, jnp.full(s, rig.threshold_on, dtype),
        jnp.full(s, rig.threshold_off, dtype), jnp.asarray(eta_nm, dtype),
    )  # fmt: skip
    return fired, tc


def initial_guess(data: ChartData, rig: Rig) -> Rig:
    """Column offsets and β from the data: first and last event time per column.

    For each chart reflectance the exact pixel model, run along the band-centre
    wavelength λc with the initial rig, gives the λc at which the first ON and the last
    OFF event of a sweep fire, λ_on and λ_off — independent of β and τx. The observed
    times t_on, t_off (first sweep) then give
    $β = (λ_{off} - λ_{on}) / (ω\\,\\mathrm{median}(t_{off} - t_{on}))$ and per column
    $τ_x = (λ_{on} - λ_0)/(βω) - t_{on}$ (medians over the column's pixels).
    """
    uniq = np.arange(data.spectra.shape[0])
    inv = data.spectrum
    fired, tc = (np.asarray(a) for a in _model_crossings(rig, data.spectra))
    tc = tc.astype(np.float64)
    omega = float(rig.omega_rad_per_us)
    dtype = rig.fwhm_nm.dtype
    any_ev = fired.any(axis=0)
    first_i = np.argmax(fired, axis=0)
    last_i = fired.shape[0] - 1 - np.argmax(fired[::-1], axis=0)
    lam_on_u = tc[first_i, np.arange(uniq.shape[0])]
    lam_off_u = tc[last_i, np.arange(uniq.shape[0])]
    lam_on, lam_off = lam_on_u[inv.ravel()], lam_off_u[inv.ravel()]
    period = float(rig.period_us)
    in_first = data.mask & (data.t_us < period)
    n_first = in_first.sum(axis=1)
    ok = any_ev[inv.ravel()] & (n_first >= 2)
    if ok.sum() < 3:
        raise ValueError(
            "too few chart pixels have events in the first sweep: is the capture lit, "
            "and do the chart and sensor size match?"
        )
    idx = np.arange(data.t_us.shape[0])
    t_on = data.t_us[:, 0]
    t_off = data.t_us[idx, np.maximum(n_first - 1, 0)]
    beta = np.median((lam_off - lam_on)[ok]) / (omega * np.median((t_off - t_on)[ok]))
    if not np.isfinite(beta) or beta <= 0:
        raise ValueError("could not estimate the sweep coefficient from the capture")
    tau_pix = (lam_on - float(rig.sweep_start_nm)) / (beta * omega) - t_on
    w = data.width
    tau = np.full(w, np.nan)
    for x in range(w):
        s = ok & (data.column == x)
        if s.any():
            tau[x] = np.median(tau_pix[s])
    good = np.isfinite(tau)
    tau = np.interp(np.arange(w), np.nonzero(good)[0], tau[good])
    return rig.with_leaves(
        beta_nm_per_rad=jnp.asarray(beta, dtype),
        column_offsets_us=jnp.asarray(tau, dtype),
    )


def calibrate(events: EventStream, chart: Scene, init: Rig, **kw) -> CalibrationResult:
    """Fit thresholds, β, c and per-column τx to a chart capture (then per-pixel maps).

    Always computed in float64 — event times of long captures and residuals of a few
    1e-4 in log units over 10⁵–10⁶ events are below float32 resolution, and the
    Levenberg–Marquardt stopping tests need it — and returned in `init`'s dtype. See
    :func:`_fit_chart_once` for the arguments (among them `sweep_speeds`: by
    default each chart sweep's mirror speed is measured, and the chart read at them
    when they differ; None reads every sweep at one speed).
    """
    import time

    t0 = time.perf_counter()
    dtype = init.fwhm_nm.dtype
    with jax.enable_x64(True):
        init64 = init.astype(jnp.float64)
        try:
            res = _fit_chart_float64(events, chart, init64, **kw)
        except NotConverged:
            # A slow photoreceptor (~1 kHz) lags events by hundreds of µs: the
            # screening and the initial guess made with the ideal model then lose
            # its late events and start τx and β too far off, and the fit does not
            # converge (40x64 chart). Once more with a slow cut-off to start from.
            if not kw.get("fit_photoreceptor", True) or init.effects.photoreceptor_hz:
                raise
            slow = init64.replace_host(photoreceptor_hz=PHOTORECEPTOR_SLOW_START_HZ)
            res = _fit_chart_float64(events, chart, slow, **kw)
        rig = res.rig.astype(dtype)
    return dataclasses.replace(res, rig=rig, seconds=time.perf_counter() - t0)


def _screened_chart_data(
    events, chart, rig, t_start_us, rows_per_label, from_data, fit_baseline,
    sweep_speeds=None,
):  # fmt: skip
    """The chart's per-pixel event lists with background activity and hot pixels
    screened out (when starting from the data), checked for enough events and
    levels: `(data, screened events, hot-pixel map)`."""
    data = chart_data(
        events, chart, rig, t_start_us=t_start_us, rows_per_label=rows_per_label,
        sweep_speeds=sweep_speeds,
    )  # fmt: skip
    if from_data:
        # Background activity and hot pixels are not in the model: find them with a
        # first guess of the sweep's timing, drop their events, then start again.
        rig0 = initial_guess(data, rig)
        events, hot, _ = screen_events(
            events, rig0, t_start_us, None, _sweeps_of(events, rig0, t_start_us),
            margin_us=SCREEN_MARGIN_US,
        )  # fmt: skip
        data = chart_data(
            events, chart, rig, t_start_us=t_start_us, rows_per_label=rows_per_label,
            sweep_speeds=sweep_speeds,
        )  # fmt: skip
    else:
        hot = np.zeros((events.height, events.width), bool)
    # Each sweep's first event refers to the sweep before, across the dark part the
    # model does not see: left out of the fit (sweep_first_events).
    first = sweep_first_events(data, float(rig.period_us))
    data = dataclasses.replace(data, mask=data.mask & ~first)
    n_on = int((data.mask & (data.polarity > 0)).sum())
    n_off = int((data.mask & (data.polarity < 0)).sum())
    if n_on < 10 or n_off < 10:
        raise ValueError(
            f"too few events to calibrate ({n_on} ON, {n_off} OFF on chart pixels); "
            "need a lit capture of the chart with at least a few events per patch"
        )
    levels = np.unique(np.round(data.spectra.mean(axis=1), 4))
    if fit_baseline and levels.size < 2:
        raise ValueError(
            "the chart has a single reflectance level: thresholds and the constant "
            "light cannot be separated (use a chart with several gray levels, or "
            "fit_baseline=False)"
        )
    return data, events, hot


#: The step of :func:`_jacobi_scale`'s differences, in the fit's parameters (log
#: thresholds, τx in `TAU_SCALE_US`, ...: all of order one at the start).
JACOBI_STEP = 1e-6


def _jacobi_scale(p0: dict, residuals, column, width: int):
    """Each parameter's Jacobian column norm at `p0` (floored): the change of variables
    of :func:`_fit_chart_float64`; and the residuals' sum of squares there.

    By forward differences of the event residuals (`residuals(params)`: one
    threshold pair, an array; `column`: each of its entries' sensor column) — one
    evaluation per global parameter and one with every τx moved at once, each
    residual depending on its own column's τx only. The norms equal the forward-mode
    derivatives' within ~1e-6 relative (48x1280 benchmark chart, 2026-11-29), all a
    preconditioner needs; the residuals' program is one the fit runs anyway, where a
    program of its own for the derivatives had been ~3.5-5 s of compilation per fit
    on a first run (twice with the band's strip)."""
    base = residuals(p0)
    h = JACOBI_STEP
    norms = {}
    for name, v in p0.items():
        if name == "tau":
            d = np.reshape((residuals({**p0, "tau": v + h}) - base) / h, -1)
            norms[name] = np.sqrt(np.bincount(np.reshape(column, -1), d * d, minlength=width))
            continue
        flat = np.asarray(v, np.float64).reshape(-1)
        col = np.zeros(flat.size)
        for i in range(flat.size):
            moved = flat.copy()
            moved[i] += h
            shifted = jnp.asarray(moved.reshape(np.shape(v)), v.dtype)
            d = (residuals({**p0, name: shifted}) - base) / h
            col[i] = np.sqrt(np.sum(np.square(d)))
        norms[name] = col.reshape(np.shape(v))
    scale = {
        k: jnp.asarray(np.maximum(v, 1e-6 * np.max(v) + 1e-30) if v.size else v,
                       p0[k].dtype)  # fmt: skip
        for k, v in norms.items()
    }
    return scale, float(np.sum(np.square(base)))


#: A Levenberg–Marquardt step whose loss equals the current one to this share of it
#: counts as accepted (`_TrustRegion`): float64 sums over ~10⁶ events carry
#: rounding of ~1e-15 of the loss.
LOSS_NOISE_RTOL = 1e-12


class _TrustRegion(optx.AbstractSearch):
    """optimistix's classical trust region (`optx.ClassicalTrustRegion`: the same
    cut-offs and factors), except that a step whose loss equals the current one
    within rounding (`LOSS_NOISE_RTOL` of it) is accepted, not rejected.

    At the optimum of a large chart the loss is flat to rounding: the actual reduction
    of a step is noise of either sign while the predicted one is ~0, so the classical
    test rejected step after step, shrinking the region until a step of ~1e-7 got
    accepted by chance and the stopping test could pass — 20 of a 48×1280 chart's 30
    steps of the profiled stage (2026-11-28), and step counts that a change of 1e-15
    in the start moved from 11 to 30. The stopping tests (`LM_TOL`) are unchanged:
    they are made on accepted steps, and a step at the optimum is now one."""

    high_cutoff: float = 0.99
    low_cutoff: float = 0.01
    high_constant: float = 3.5
    low_constant: float = 0.25

    def init(self, y, f_info_struct):
        return jnp.array(1.0)  # the step size

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        y_diff = jax.tree.map(lambda a, b: a - b, y_eval, y)
        res = f_info.residual
        moved = jax.tree.map(lambda a, b: a + b, f_info.jac.mv(y_diff), res)
        predicted = 0.5 * (_sum_squares(moved) - _sum_squares(res))
        f_min = f_info.as_min()
        diff = f_eval_info.as_min() - f_min  # negative: a reduction
        flat = jnp.abs(diff) <= LOSS_NOISE_RTOL * jnp.abs(f_min)
        accept = (diff <= self.low_cutoff * predicted) | flat | first_step
        good = (diff < self.high_cutoff * predicted) & (predicted < 0) & ~first_step
        mul = jnp.where(good, self.high_constant, 1.0)
        mul = jnp.where(accept, mul, self.low_constant)
        size = mul * state
        return size, accept, optx.RESULTS.successful, size


def _sum_squares(tree):
    """Σ of squares over a pytree's leaves."""
    return sum(jnp.sum(jnp.square(a)) for a in jax.tree.leaves(tree))


def _lm_stage(u, scale, profile, keep, fit, max_steps, verbose, tol):
    """One Levenberg–Marquardt stage of :func:`_fit_chart_float64` from the scaled
    start `u`: (its end point, its number of steps, whether it converged). A function
    of arrays and static values only, so that `call_exported` can keep its traced
    program on disk: tracing optimistix's solver is most of a small chart's
    calibration time in a new process. `profile` (a boolean array) and `tol`
    (`(rtol, atol)`, an array) are inputs, so both stages run one program: a first
    run compiles it once (with two programs, ~5 s more on 2 cores)."""
    solver = optx.LevenbergMarquardt(
        rtol=tol[0],
        atol=tol[1],
        # An inexact Gauss–Newton step is enough inside Levenberg–Marquardt.
        linear_solver=_normal_cg(rtol=1e-4, atol=1e-9),
        verbose=verbose,
    )
    solver = eqx.tree_at(lambda s: s.search, solver, _TrustRegion())
    sol = optx.least_squares(
        _fit_residuals_scaled,
        solver,
        u,
        args=(scale, (profile, keep, fit)),
        max_steps=max_steps,
        throw=False,
    )
    return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


def _fit_chart_float64(
    events: EventStream, chart: Scene, init: Rig, **kw
) -> CalibrationResult:
    """:func:`_fit_chart_once` (the arguments are its), and when it found the chart's
    sweeps running at speeds that differ by more than their estimate's error, once
    more with each sweep's events read at its own speed (then the rig's
    `sweep_rate_jitter` is their spread). Should that second fit fail (it raises a
    `ValueError`), the chart is fitted at one speed as before and the result says so
    (:attr:`CalibrationResult.sweep_speed_note`). The second fit runs after the first
    one's data are released: a full 1280×720 chart's screened stream alone is ~0.6 GB.
    """
    import time

    t0 = time.perf_counter()
    res = _fit_chart_once(events, chart, init, **kw)
    if not isinstance(res, ChartSpeeds):
        return res
    found = res
    if kw.get("verbose"):
        print(f"calibrate: the chart's sweeps differ in speed (spread "
              f"{found.jitter:.2e}): fitted again at each sweep's own")  # fmt: skip
    try:
        res = _fit_chart_once(events, chart, init, **dict(kw, sweep_speeds=found))
    except ValueError as err:  # (NotConverged too): one speed, as before
        if kw.get("verbose"):
            print(f"calibrate: the fit at the sweeps' speeds failed ({err})")
        res = _fit_chart_once(events, chart, init, **dict(kw, sweep_speeds=None))
        res = dataclasses.replace(res, sweep_speeds=found)
    return dataclasses.replace(res, seconds=time.perf_counter() - t0)


def _fit_chart_once(
    events: EventStream,
    chart: Scene,
    init: Rig,
    *,
    t_start_us: int | None = None,
    rows_per_label: int | None = 4,
    per_pixel: bool = True,
    max_steps: int = 100,
    fit_baseline: bool = True,
    from_data: bool = True,
    response_degree: int = 4,
    fit_curvature: bool = True,
    fit_photoreceptor: bool = True,
    fit_band: bool | None = None,
    verbose: bool = False,
    maps: bool = True,
    noise: bool = True,
    sweep_speeds: ChartSpeeds | str | None = "measure",
) -> CalibrationResult | ChartSpeeds:
    """Fit thresholds, β, c and per-column τx to a chart capture (then per-pixel maps).

    **Arguments:**

    - `events`: capture of `chart` (one or more sweeps); `init`: the initial rig.
    - `t_start_us`: sweep phase 0 (default: first trigger, else 0).
    - `rows_per_label`: rows of each patch used for the global fit (per column).
    - `per_pixel`: also estimate per-pixel threshold maps (all pixels).
    - `max_steps`: Levenberg–Marquardt steps per stage (100; 60 until the band
      profile was fitted, whose stage took 45–55 steps on small charts).
    - `fit_baseline`: fit c (else kept).
    - `from_data`: start β and τx from :func:`initial_guess` instead of `init`'s.
    - `response_degree`: fit a smooth correction of the camera response,
      $D(λ) \\exp(\\sum_{j=1}^{n} w_j P_j)$ (Legendre polynomials over the channel range):
      a gray chart sees D·E through the shape of its intensity traces, so a wrong D would
      otherwise bias everything else. 0 keeps D.
    - `fit_curvature`: fit the sweep's parabolic non-linearity `sweep_curvature_nm`
      (the band's entry and exit anchor the ends; the lamp's and camera's spectral
      structure inside the range places the middle).
    - `fit_photoreceptor`: measure the photoreceptor's low-pass cut-off
      `photoreceptor_hz` (starting from `init`'s, or `PHOTORECEPTOR_START_HZ` when it
      has none; see :func:`_cutoff`); a cut-off above `PHOTORECEPTOR_IDEAL_HZ` after
      the first stage counts as none, and the fit goes on with the ideal sensor's
      model. False keeps `init`'s.
    - `fit_band`: fit the band profile `band_profile` — a smooth correction
      (`BAND_KNOTS` knots of log T) of `init`'s profile, or of the Gaussian of its
      `fwhm_nm` — in the last stage. A gray chart sees the band's shape where the
      band enters and leaves the channel range: its intensity there is the
      profile's cumulative integral, sampled by many threshold crossings. Its centroid
      is kept (τx absorbs a common shift). None (default): fitted when `init` gives
      no `band_profile` and `per_pixel`, kept when it does (a profile measured with
      a spectrometer).
    - `maps`: with `per_pixel`, also the per-pixel threshold maps and the PSF
      (False: the profiled stage only, as for the band's strip).
    - `noise`: measure the sensor's noise (per-crossing threshold noise, timestamp
      jitter, background rate; False: zeros, as for the band's strip, whose rig
      only gives the band and a start).
    - `sweep_speeds`: each sweep's mirror speed. `"measure"` (default, with `maps` and
      `noise`): after the fit, :func:`._chart.chart_sweep_speeds` measures them
      with the fitted rig; when they differ by more than the estimate's error (a
      mirror with `sweep_rate_jitter`) this returns them instead of a result, for
      :func:`_fit_chart_float64` to fit the chart again at them. A
      :class:`._chart.ChartSpeeds`: read the sweeps at those; None: every sweep at
      the rig's speed.

    **Returns:** a :class:`CalibrationResult` (or the :class:`._chart.ChartSpeeds`
    found, above).
    """
    import time

    if isinstance(sweep_speeds, str) and sweep_speeds != "measure":
        raise ValueError(
            f"sweep_speeds must be 'measure', None or a ChartSpeeds, not {sweep_speeds!r}"
        )

    t0 = time.perf_counter()
    given = sweep_speeds if isinstance(sweep_speeds, ChartSpeeds) else None
    if fit_band is None:
        # (Not with one threshold pair for all pixels: the band's shape then chases
        # the pixels' threshold spread.)
        fit_band = init.band_profile is None and per_pixel
    band_fitted, photoreceptor_fitted = fit_band, fit_photoreceptor
    band_tried = fit_band
    if fit_band and events.width > max(BAND_DIRECT_COLUMNS, BAND_CROP_COLUMNS):
        init, band_fitted = _band_from_strip(
            events, chart, init, t_start_us=t_start_us, rows_per_label=rows_per_label,
            max_steps=max_steps, fit_baseline=fit_baseline, from_data=from_data,
            response_degree=response_degree, fit_curvature=fit_curvature,
            fit_photoreceptor=fit_photoreceptor, verbose=verbose, sweep_speeds=given,
        )  # fmt: skip
        fit_band = False
        if fit_photoreceptor and not init.effects.photoreceptor_hz:
            # The strip found no low-pass worth modelling: so is the whole chart's
            # sensor (its fit would walk the cut-off from its start to none again).
            fit_photoreceptor = False
    w = events.width
    rig = _with_column_offsets(init, w)
    if rig.column_offsets_us.shape[0] != w:
        raise ValueError(
            f"initial rig has {rig.column_offsets_us.shape[0]} column offsets, the "
            f"capture is {w} columns wide"
        )
    if t_start_us is None:
        t_start_us = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    captured = events
    data, events, hot = _screened_chart_data(
        events, chart, rig, t_start_us, rows_per_label, from_data, fit_baseline, given
    )
    if from_data:
        rig = initial_guess(data, rig)
    dtype = rig.fwhm_nm.dtype
    basis = _response_basis(rig, response_degree)
    fixed_traces = (  # the table's values (a BandTable is not a pytree leaf holder)
        None
        if response_degree or fit_band
        else spectral_traces(rig, data.spectra).values
    )
    hz0 = rig.effects.photoreceptor_hz
    if fit_photoreceptor:
        # The fit's rig carries the reference cut-off, so its programs do not
        # depend on the start (see _cutoff).
        start_hz = hz0 if hz0 > 0 else PHOTORECEPTOR_START_HZ
        rig = with_reference_cutoff(rig)
    p0 = {
        "log_on": jnp.zeros((), dtype),
        "log_off": jnp.zeros((), dtype),
        "log_beta": jnp.zeros((), dtype),
        "log_c": jnp.zeros((), dtype),
        **({"curv": jnp.zeros((), dtype)} if fit_curvature else {}),
        "tau": jnp.zeros((w,), dtype),
        "resp": jnp.zeros((response_degree,), dtype),
        **(
            {"pr": jnp.asarray(PHOTORECEPTOR_REF_HZ / start_hz, dtype)}
            if fit_photoreceptor
            else {}
        ),
        **({"band": jnp.zeros((BAND_KNOTS,), dtype)} if fit_band else {}),
    }

    # Everything the residuals read travels as arguments (not closed over), so each
    # compiled function depends on shapes only: one compilation per shape in a
    # process, and the persistent cache serves the next process.
    overlap = band_overlap(rig)
    blocks, layout = _packed(data, dtype)
    n_px = data.t_us.shape[0]
    # Pixels in the fit (outliers: False), and at their events' slots (see _FitData).
    keep_px = np.ones(n_px, bool)
    keep = ones = layout.per_slot(keep_px, dtype)
    band = _band_start(rig, dtype) if fit_band else None
    spectra = jnp.asarray(data.spectra, dtype)

    def fit_data(band, gate):
        return _fit_data(rig, basis, blocks, spectra, fixed_traces, overlap, band,
                         gate, fit_baseline)  # fmt: skip

    def lm_args(u, scale, fit, profile, tol):  # (`keep`: the current one)
        return (u, scale, jnp.asarray(profile), keep, fit, max_steps, bool(verbose), tol)

    def solve(*a):
        # (verbose prints from inside the solve: a host callback, which an exported
        # program cannot hold)
        if verbose:
            return _lm_stage(*lm_args(*a))
        return call_exported("calibrate_lm", _lm_stage, lm_args(*a))

    fit = fit_data(band, jnp.ones((), dtype))

    def slot_residuals(params, profile, keep):  # (n_blocks, E), the packed slots
        # (`profile` as an array: one program for both kinds of residual)
        args = (params, jnp.asarray(profile), keep, fit)
        return np.asarray(call_exported("calibrate_residuals", _fit_residuals, args))

    def residuals(params, profile, keep):  # (n_px, k), the chart's lists
        return layout.to_lists(slot_residuals(params, profile, keep))

    def rms_of(sum_sq, keep_px):  # over the events of the kept pixels
        n = int((data.mask & keep_px[:, None]).sum())
        return float(np.sqrt(sum_sq / max(n, 1)))

    def sum_sq(res):
        return float(np.sum(np.square(res, dtype=np.float64)))

    if not verbose:
        # The residuals' and the solver's programs compile in a background thread
        # while this one goes on (a first run spent ~20 s of a 48x1280 chart's
        # calibration compiling these, twice with the band's strip; XLA's compiler
        # keeps ~1.7 of 2 cores busy by itself, so what overlaps is mostly this
        # thread's Python). Only their shapes matter: p0 stands for u and s.
        prepare_exported(
            "calibrate_residuals", _fit_residuals, (p0, jnp.asarray(False), keep, fit)
        )
        tol0 = jnp.asarray(LM_TOL[0], dtype)
        prepare_exported("calibrate_lm", _lm_stage, lm_args(p0, p0, fit, False, tol0))
    # Jacobi scaling by change of variables (u = θ·s, s = column norms of the Jacobian at
    # the start): the Gauss–Newton matrix then has a unit diagonal and is "identity plus
    # the rank-4 coupling of the global parameters", so the matrix-free CG inside each
    # Levenberg–Marquardt step converges in a few iterations.
    scale, ss0 = _jacobi_scale(
        p0, lambda p: slot_residuals(p, False, keep), layout.column, w
    )
    r0 = rms_of(float(ss0), keep_px)
    # Stage 1: one threshold pair for all pixels. Stage 2 (per_pixel): the same fit with
    # every pixel's thresholds profiled out, so per-pixel mismatch cannot bias β, c, τx;
    # the thresholds then follow in closed form and the rig's global pair is their mean.
    u, steps = jax.tree.map(lambda a, b: a * b, p0, scale), 0
    converged = True
    outlier_pixels = 0
    stages = (False, True) if per_pixel else (False,)
    for profile in stages:
        last = profile == stages[-1]  # a start for the next stage, or the answer
        # The band's shape is fitted in the last stage only: with one threshold pair
        # the first stage's misfit is the pixels' threshold spread, which the band's
        # shape then chased (74 steps on a 32x48 chart, against 31 without it).
        gate = jnp.asarray(float(last), dtype)
        fit = eqx.tree_at(lambda f: f.band_gate, fit, gate)
        tol = jnp.asarray(LM_TOL[int(last)], dtype)
        u_start = u
        u, n_steps, ok = solve(u, scale, fit, profile, tol)
        steps += int(n_steps)
        if last and not bool(ok) and band is not None:
            # The band's shape is not determined by this capture: its fit crawls
            # along a flat valley (a 32x48 chart with 15 µs of timestamp jitter:
            # the loss fell by 1e-7 of itself over 90 steps while the knots kept
            # moving). The stage again with the band kept, as with `fit_band=False`
            # (the exact overlap table, the parameter gone: one more program).
            if verbose:
                print("calibrate: the band profile's fit did not converge; kept")
            band, band_fitted = None, False
            u = {k: v for k, v in u_start.items() if k != "band"}
            scale = {k: v for k, v in scale.items() if k != "band"}
            fit = fit_data(None, gate)
            u, n_steps, ok = solve(u, scale, fit, profile, tol)
            steps += int(n_steps)
        converged = bool(ok)
        params = _unscale(u, scale)
        if not all(bool(jnp.all(jnp.isfinite(v))) for v in jax.tree.leaves(params)):
            raise ValueError("the calibration diverged (non-finite parameters)")
        if "pr" in params and float(_cutoff(params)) > PHOTORECEPTOR_IDEAL_HZ:
            # No low-pass worth modelling: the ideal sensor's model from here on.
            # The next stage keeps the parameter, pinned where the filter is off
            # (pr < 0: its column of the Jacobian is zero, so it does not move), so
            # that both stages run one compiled program; the maps and `reconstruct`
            # get the ideal sensor's exact model.
            if verbose and float(params["pr"]) != -1.0:  # (-1: pinned already)
                print(
                    "calibrate: no low-pass worth modelling (cut-off above "
                    f"{PHOTORECEPTOR_IDEAL_HZ:.0f} Hz): the ideal sensor's model"
                )
            u = dict(u, pr=-scale["pr"])
            params = _unscale(u, scale)
        if verbose and "pr" in params and params["pr"] > 0:
            print(f"calibrate: cut-off {float(_cutoff(params)):.1f} Hz")
        if verbose:
            print(
                f"calibrate (profiled={profile}): "
                f"{'converged' if converged else 'not converged'} after "
                f"{int(n_steps)} steps, rms "
                f"{rms_of(sum_sq(residuals(params, profile, keep)), keep_px):.5f}"
            )
        if not profile:
            # Robustness: a pixel with an event the model cannot explain (a noise
            # event inside the lit interval, a missed crossing) is dropped whole —
            # one bad event also corrupts its neighbour's reference.
            r = residuals(params, per_pixel, ones)
            bad_px = _outlier_pixels(r, data.mask)
            outlier_pixels = int(bad_px.sum())
            if 0 < outlier_pixels < 0.5 * bad_px.size:
                keep_px = ~bad_px
                keep = layout.per_slot(keep_px, dtype)
    res_final = residuals(params, per_pixel, keep)
    rms = rms_of(sum_sq(res_final), keep_px)
    data = dataclasses.replace(data, mask=data.mask & keep_px[:, None])
    fitted = _apply(params, rig, basis)
    if not fit_baseline:
        fitted = fitted.with_leaves(baseline_rel=rig.baseline_rel)
    if band is not None:
        fitted = fitted.with_band_profile(fitted_band_profile(params["band"], band))
    if "pr" in params:
        hz = float(_cutoff(params))
        fitted = fitted.replace_host(
            photoreceptor_hz=hz if hz <= PHOTORECEPTOR_IDEAL_HZ else 0.0
        )
    found = given
    if isinstance(sweep_speeds, str) and per_pixel and maps and noise:  # ("measure")
        found = chart_sweep_speeds(
            events, chart, fitted, t_start_us=t_start_us, rows_per_label=rows_per_label
        )
        if found is not None and found.significant:
            return found  # (_fit_chart_float64 fits again at them)
    on_map = off_map = psf = None
    if per_pixel and maps:
        # The compiler's freed memory back to the system before the maps' own peak
        # (a first run, which compiles, held ~0.5 GB of it here).
        release_free_memory()
        on_map, off_map, psf = threshold_maps_from_chart(
            events, chart, fitted, t_start_us=t_start_us, return_psf=True, sweep_speeds=given
        )
        # The population thresholds: mean over the chart pixels that had such events.
        c_on, c_off = _closed_form_thresholds(_log_steps(fitted, data), data)
        fitted = fitted.with_leaves(
            threshold_on=jnp.asarray(np.nanmean(c_on), dtype),
            threshold_off=jnp.asarray(np.nanmean(c_off), dtype),
        )
    if noise:
        measured = measure_noise(fitted, data, res_final)
        bg_rate = _background_rate(captured, hot, fitted, t_start_us)
    else:
        measured = {"threshold_noise": 0.0, "timestamp_jitter_us": 0.0}
        bg_rate = 0.0
    if rms > MAX_RMS_RESIDUAL:
        raise ValueError(
            f"the calibration does not fit its data: RMS residual {rms:.2f} thresholds "
            f"after {steps} steps (a gray-chart capture of this rig fits to < "
            f"{MAX_RMS_RESIDUAL}); is the capture a gray chart of the given size, "
            "lit by the sweep?"
        )
    if not converged:
        raise NotConverged(
            f"the calibration did not converge: Levenberg–Marquardt stopped after "
            f"{steps} steps (limit {max_steps} per stage) at RMS residual {rms:.3f} "
            "thresholds; is the capture a gray chart of this rig? (max_steps raises "
            "the limit)"
        )
    fitted = fitted.replace_host(
        threshold_noise=measured["threshold_noise"],
        timestamp_jitter_us=measured["timestamp_jitter_us"],
        sweep_rate_jitter=0.0 if given is None else min(given.jitter, 0.01),
        noise_rate_hz=bg_rate,
        **({} if psf is None else {"psf_sigma_px": psf}),
    )
    return CalibrationResult(
        rig=fitted,
        threshold_on_map=on_map,
        threshold_off_map=off_map,
        hot_pixels=hot,
        converged=bool(converged),
        outlier_pixels=outlier_pixels,
        rms_residual=rms,
        rms_residual_initial=r0,
        steps=steps,
        events_used=data.events,
        pixels_used=int(data.mask.any(axis=1).sum()),
        seconds=time.perf_counter() - t0,
        psf_sigma_px=psf,
        photoreceptor_fitted=photoreceptor_fitted,
        band_fitted=band_fitted,
        band_unresolved=band_tried and not band_fitted,
        sweep_speeds=found,
        sweep_speeds_used=given is not None,
    )


def _band_from_strip(
    events: EventStream, chart: Scene, init: Rig, sweep_speeds=None, **kw
) -> tuple[Rig, bool]:
    """`init` with the band profile of a calibration of the chart's middle
    `BAND_CROP_COLUMNS` columns (all rows; `kw` as :func:`_fit_chart_float64`'s),
    and its other global values as the whole chart's start: thresholds, c, D(λ),
    the sweep's curvature and the photoreceptor's cut-off (τx and β are the whole
    chart's: its initial guess); and whether the band was fitted (else `init`'s is
    kept: its fit on the strip did not converge)."""
    w = events.width
    x0 = (w - BAND_CROP_COLUMNS) // 2
    roi = (x0, 0, x0 + BAND_CROP_COLUMNS, events.height)
    offs = np.asarray(init.column_offsets(w), np.float64)[x0 : x0 + BAND_CROP_COLUMNS]
    strip = dataclasses.replace(chart, labels=np.asarray(chart.labels)[:, roi[0] : roi[2]])
    sub = _fit_chart_float64(
        events.crop(roi),
        strip,
        init.with_leaves(column_offsets_us=jnp.asarray(offs, init.fwhm_nm.dtype)),
        per_pixel=True,
        fit_band=True,
        maps=False,
        noise=False,
        sweep_speeds=None
        if sweep_speeds is None
        else sweep_speeds.columns(x0, x0 + BAND_CROP_COLUMNS),
        **kw,
    )
    release_free_memory()  # the strip's compiler memory, before the whole chart's
    if kw.get("verbose") and sub.band_fitted:
        print(f"calibrate: band profile fitted on columns {roi[0]}-{roi[2] - 1}")
    r = sub.rig
    start = init.with_leaves(
        threshold_on=r.threshold_on,
        threshold_off=r.threshold_off,
        baseline_rel=r.baseline_rel,
        camera_response=r.camera_response,
        sweep_curvature_nm=r.sweep_curvature_nm,
    )
    if kw.get("fit_photoreceptor", True):
        start = start.replace_host(photoreceptor_hz=float(r.effects.photoreceptor_hz))
    if not sub.band_fitted:
        return start, False
    off, val = r.band_profile
    return start.with_band_profile({"offset_nm": list(off), "values": list(val)}), True


def save_calibration(path, result: CalibrationResult, *, comment: str = "") -> dict:
    """Write a calibration file pair (:meth:`Calibration.save`): the rig JSON with every
    key and the measured sensor noise, and a sibling `<stem>_thresholds.npz` with the
    per-pixel maps that the JSON names. Both atomic.

    **Returns:** the JSON object written.
    """
    cal = result.calibration
    report = dict(cal.report)
    report["comment"] = (
        (comment + ": " if comment else "")
        + f"rms residual {result.rms_residual:.2e} (start "
        f"{result.rms_residual_initial:.2e}) thresholds over {result.events_used} events "
        f"of {result.pixels_used} pixels, {result.steps} LM steps, {result.seconds:.0f} s"
    )
    return dataclasses.replace(cal, report=report).save(path)


def spectral_correction(
    cube: np.ndarray, reference: np.ndarray, *, floor: float = 0.05
):
    """Per-channel response factors from a white reference (paper supplement 6.1).

    Reconstruct a capture of a reference of known spectrum with the calibrated rig;
    whatever makes the reconstruction differ from the reference in the same way at every
    pixel — a camera response D(λ) different from the rig's, or any other systematic
    per-channel error — appears as the ratio reconstruction / truth. The factors are the
    median over pixels of that ratio per channel. Store them as the rig's
    `channel_gain` (:func:`apply_spectral_correction`); reconstructions are then divided
    by them. (An error of D within a channel scales that channel's A(t) column, hence its
    reconstructed value, by the same factor, so the correction acts on the output and
    leaves the forward model — and the calibrated c and thresholds — untouched.)

    **Arguments:**

    - `cube`: reconstruction of the reference capture, `(H, W, M)`.
    - `reference`: the reference's true reflectance on the channel grid, `(M,)` or
      `(H, W, M)`.
    - `floor`: channels where the reference is below this reflectance get factor 1.

    **Returns:** factors, shape `(M,)`.
    """
    cube = np.asarray(cube, np.float64)
    ref = np.broadcast_to(np.asarray(reference, np.float64), cube.shape)
    ok = ref > floor
    ratio = np.where(ok, cube / np.where(ok, ref, 1.0), np.nan)
    with np.errstate(invalid="ignore"):
        f = np.nanmedian(ratio.reshape(-1, cube.shape[-1]), axis=0)
    return np.where(np.isfinite(f) & (f > 0), f, 1.0)


def apply_spectral_correction(rig: Rig, factors) -> Rig:
    """A rig whose reconstructions are divided by per-channel `factors` (M,), combined
    with any correction it already has (the factors multiply)."""
    f = np.asarray(factors, np.float64)
    if f.shape != (rig.channels,) or np.any(~np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"need {rig.channels} positive finite correction factors")
    f = f * np.asarray(rig.channel_gain)  # (ones when there is no correction yet)
    return rig.replace_host(channel_gain=[float(v) for v in f])
