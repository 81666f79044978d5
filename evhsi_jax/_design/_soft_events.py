"""Events of training pixels as a differentiable function of the design.

**Why not the soft model's expected counts for the event times.** The reconstruction
needs a list of events (time, polarity, reference). The exact pixel state machine gives
it; its *discrete* part — how many events, which polarity, in which order — is piecewise
constant in the design, and its *continuous* part — when each event fires — is a smooth
function of the design between changes of structure. So:

1. **Structure** from the exact scan (:func:`~evhsi_jax.forward.exact_events_scan`) on a fine
   grid of band positions λc, held fixed (stop-gradient) at each evaluation.
2. **Times by the implicit function theorem.** Event k satisfies
   $g_k = L(τ_k) - L(τ_{k-1} + η) - σ_k C = 0$ ($L = \\log(I + ε)$ of the pixel, cubic
   table interpolation, the reference at the end of the previous refractory period).
   One Newton step with frozen slope, $τ_k^\\star = τ_k - g_k(τ_k, τ_{k-1}^\\star; θ)
   / \\mathrm{sg}(∂g_k/∂τ_k)$, scanned over k, has the value τ_k and exactly the IFT
   derivative $dτ_k/dθ = -(∂g_k/∂θ + ∂g_k/∂τ_{k-1}\\,dτ_{k-1}/dθ)/(∂g_k/∂τ_k)$
   (the slope is clamped away from 0: near a turning point the true derivative is
   infinite). The sensor's 1 µs timestamps enter as a fixed dither: slot k's time is
   offset by $d_k \\in [-½, ½)$ µs (a low-discrepancy sequence, independent of the
   design), which has the statistics of rounding to whole µs but keeps the loss a
   smooth function of the design between changes of structure, so that its autodiff
   gradient equals its finite differences (true rounding would be piecewise constant
   in the event times; at the default sweep 1 µs moves the band by 0.017 nm).
3. **Smooth existence of marginal events.** Held-fixed structure alone is blind to what
   the design does to the *number* of events — lowering C or c adds events, the main
   way they lower the error. Events are born and die at turning points of L, where the
   excursion beyond the reference just reaches C. Each event gets the weight
   $\\mathrm{sigmoid}(m_k/T)$ of its margin $m_k = \\max σ_k(L - L(ρ_k)) - C$ over the
   gap after it, and each gap the would-be event of the other polarity at its
   extremum (a *ghost*, margin = excursion − C < 0) with $\\mathrm{sigmoid}(m/T)$. In
   the lattice picture a new event at a turning point brings a second one — the
   crossing back through the old reference level — so a ghost comes with that partner
   and a marginal event's weight also multiplies the next (opposite) event. Rows of
   ghosts use the actual log step, so they are exact constraints. At a change of
   structure the weights meet at ½ from both sides: the loss changes continuously
   across the part of the change the rows see (the anti-drift prior's gap structure
   still jumps), and its gradient carries the count effect — that of a threshold
   jitter of scale T.

The soft event model (:func:`~evhsi_jax.forward.soft_event_counts`) gives the expected event
count for the event-rate limit.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._model import BandTable, Rig, band_table, exact_events_scan, lookup
from .._reconstruct import PixelEvents, ProblemConfig, pixel_system

__all__ = ["StructureConfig", "band_grid", "pixel_traces", "hard_events", "pixel_qp"]

_NEG = -1e3  # "no point" in a segment maximum, log units
_SLOPE_FLOOR = 1e-6  # log units per µs: 1/(slope) ≤ 1e6 µs per log unit
_POLISH = 3  # Newton steps polishing each crossing time (value only)
_GOLDEN = 0.6180339887498949  # timestamp dither: frac(k φ) is evenly spread


def sg(x):
    return jax.lax.stop_gradient(x)


@dataclasses.dataclass(frozen=True)
class StructureConfig:
    """Static sizes and settings of the differentiable event structure.

    - `n_steps`: λc grid steps over the channels ± 3 FWHM (time step ≤ refractory).
    - `max_events`: event slots per pixel (more are dropped and counted).
    - `smoothing`: T of the existence weights, log units (> 0): they give the smooth
      event count behind the event-rate limit.
    - `weighted_rows`: also weight the QP's event rows by existence and add the ghost
      rows (False: the QP sees the held structure alone — the pure implicit-function
      gradient of the exact pipeline's error).
    - `width`: sensor width for the column offsets τx.
    - `fwhm_bound_nm`: static bound of the traced FWHM (band table size).
    """

    n_steps: int = 4096
    max_events: int = 96
    smoothing: float = 0.01
    weighted_rows: bool = True
    width: int = 1280
    fwhm_bound_nm: float = 50.0


def band_grid(rig: Rig, n_steps: int):
    """Band positions `lam` (N+1,) over the channels ± 3 FWHM and their times
    $t' = (λ - λ_0)/v$ in µs (a column's time is $t' - τ_x$)."""
    dtype = rig.fwhm_nm.dtype
    lo = rig.grid.start_nm - 3.0 * rig.fwhm_nm
    hi = rig.grid.stop_nm + 3.0 * rig.fwhm_nm
    lam = lo + (hi - lo) * (jnp.arange(n_steps + 1, dtype=dtype) / n_steps)
    speed = rig.band_speed_nm_per_us  # nm/µs
    return lam, (lam - rig.sweep_start_nm) / speed


def pixel_traces(
    rig: Rig, spectra_fine: Float[Array, "p f"], fwhm_bound_nm: float
) -> BandTable:
    """Intensity above c of each training pixel vs band centre: a `(n, p)` table."""
    tab = band_table(rig, fwhm_bound_nm=fwhm_bound_nm)
    vals = tab.values @ spectra_fine.T.astype(tab.values.dtype)
    return BandTable(vals, tab.lo_nm, tab.step_nm)


def hard_events(
    log_i: Float[Array, "n1 p"],
    t_local: Float[Array, " n1"],
    threshold: Float[Array, " p"],
    refractory_us: Float[Array, ""],
    max_events: int,
):
    """The exact scan's events, first `max_events` per pixel (no gradient).

    **Returns:** `(step, t, polarity, mask, count)`: step index `(p, k)` (`n + 1` in
    padding), crossing time in the $t'$ frame `(p, k)`, ±1 `(p, k)` int32, real-event
    mask `(p, k)`, and all events per pixel `(p,)`.
    """
    thr = threshold
    (fired, tc, up), _ = exact_events_scan(
        sg(log_i), sg(t_local), sg(thr), sg(thr), sg(refractory_us)
    )
    n = fired.shape[0]
    j = jnp.arange(n)[:, None]
    order = jnp.argsort(jnp.where(fired, j, n + j), axis=0)[:max_events]
    mask = jnp.take_along_axis(fired, order, 0).T
    step = jnp.where(mask, order.T, n + 1)
    t = jnp.take_along_axis(tc, order, 0).T
    sign = jnp.where(jnp.take_along_axis(up, order, 0).T, 1, -1)
    pol = jnp.where(mask, sign, 0).astype(jnp.int32)
    return step, t, pol, mask, jnp.sum(fired, axis=0)


def _log_sig(x):
    return jax.nn.log_sigmoid(x)


def pixel_qp(
    rig: Rig,
    channel_table: BandTable,
    trace_col: Float[Array, " n"],
    trace_lo_nm: float,
    trace_step_nm: float,
    cfg: ProblemConfig,
    scfg: StructureConfig,
    lam: Float[Array, " n1"],
    t_local: Float[Array, " n1"],
    log_col: Float[Array, " n1"],
    step: Int[Array, " k"],
    t_cross: Float[Array, " k"],
    pol: Int[Array, " k"],
    mask: Bool[Array, " k"],
    offset_us: Float[Array, ""],
):
    """One training pixel's box QP `(Q, q)` as a differentiable function of the rig.

    `trace_col` is the pixel's column of :func:`pixel_traces`, `log_col` its log level
    on the grid, `step … mask` its hard events (the $t'$ frame), `offset_us` its τx.

    **Returns:** `(Q, q, smooth_count)` — the QP (event rows weighted by existence,
    plus ghost rows) and the expected event count under the existence weights.
    """
    dtype = log_col.dtype
    k_slots = step.shape[0]
    n1 = lam.shape[0]
    base = rig.baseline_level
    speed = rig.band_speed_nm_per_us
    eta = rig.refractory_us
    thr = 0.5 * (rig.threshold_on + rig.threshold_off)
    trace = BandTable(trace_col[:, None], trace_lo_nm, trace_step_nm)

    def centre(t):
        return rig.sweep_start_nm + speed * (t + offset_us)

    def level(t):
        a = lookup(trace, centre(t), order=3)[..., 0]
        return jnp.log(jnp.maximum(a, 0.0) + base)

    # --- event times by the implicit function theorem ------------------------------
    tau = sg(t_cross - offset_us)
    sgn = pol.astype(dtype)
    l_start = log_col[0]
    first = jnp.arange(k_slots) == 0
    dt = sg(t_local[1] - t_local[0])
    d_level = jax.grad(level)

    def frozen_slope(t, s_k, mk):
        sl = sg(d_level(t))
        return jnp.where(mk, s_k * jnp.maximum(s_k * sl, _SLOPE_FLOOR), 1.0)

    def newton(prev, inp):
        t_k, s_k, mk, is_first = inp
        ref = jnp.where(is_first, l_start, level(prev + eta))
        # The scan's crossing interpolates the grid linearly; polish it on the cubic
        # trace (no gradient) so that the IFT step below starts from a root.
        t_hat = t_k
        for _ in range(_POLISH):
            g0 = sg(level(t_hat) - ref - s_k * thr)
            t_hat = t_hat - jnp.clip(g0 / frozen_slope(t_hat, s_k, mk), -dt, dt)
        g = level(t_hat) - ref - s_k * thr
        t_star = jnp.where(mk, t_hat - g / frozen_slope(t_hat, s_k, mk), prev)
        return t_star, t_star

    _, t_star = jax.lax.scan(newton, jnp.zeros((), dtype), (tau, sgn, mask, first))
    dither = jnp.mod(jnp.arange(k_slots, dtype=dtype) * _GOLDEN + 0.5, 1.0) - 0.5
    t_obs = jnp.where(mask, t_star + dither, 0.0)
    n_ev = jnp.sum(mask)

    # --- gaps: interval i runs from event i-1 to event i (0: start, k: tail) --------
    t_rel = jnp.concatenate([jnp.zeros((1,), dtype), t_star + eta])  # (k+1,)
    r_int = jnp.concatenate([l_start[None], jax.vmap(level)(t_star + eta)])
    j = jnp.arange(n1)
    iid = jnp.searchsorted(step, j, side="left")  # events with step < j
    t_grid = t_local - offset_us
    live = (t_grid >= t_rel[iid]) | (iid == 0)
    r_g = r_int[iid]
    segs = k_slots + 1

    def seg_max(v):
        return jnp.maximum(jax.ops.segment_max(v, iid, num_segments=segs), _NEG)

    def seg_arg(v, vmax):
        return jax.ops.segment_max(
            jnp.where(v >= vmax[iid], j, -1), iid, num_segments=segs
        )

    # Margins of real events: the largest excursion beyond their reference in the gap
    # after them (interval k+1 for slot k), minus C.
    sgn_open = jnp.concatenate([jnp.zeros((1,), dtype), sgn])[iid]
    r_open = jnp.concatenate([jnp.zeros((1,), dtype), r_int[:-1]])[iid]
    excess = jnp.where(iid >= 1, sgn_open * (log_col - r_open), _NEG)
    margin = seg_max(excess)[1:] - thr
    log_e = _log_sig(margin / scfg.smoothing)
    prev_log_e = jnp.concatenate([jnp.zeros((1,), dtype), log_e[:-1]])
    prev_sgn = jnp.concatenate([jnp.zeros((1,), dtype), sgn[:-1]])
    log_w = log_e + jnp.where(prev_sgn * sgn < 0, prev_log_e, 0.0)
    scale = jnp.where(mask, jnp.exp(0.5 * log_w), 0.0)

    count_rows = jnp.sum(jnp.where(mask, jnp.exp(log_w), 0.0))
    q_mat, q_vec, _ = pixel_system(
        rig,
        channel_table,
        cfg,
        PixelEvents(
            t_obs,
            pol,
            mask,
            offset_us,
            rig.threshold_on,
            rig.threshold_off,
            jnp.zeros((), dtype),
        ),
        1,
        event_scale=scale if scfg.weighted_rows else None,
    )

    # --- ghosts: the other polarity's would-be event at each gap's extremum ---------
    ends = jnp.concatenate([sgn, jnp.zeros((1,), dtype)])  # polarity ending gap i
    gap = jnp.arange(segs)
    valid = gap <= n_ev
    t_ref_row = jnp.concatenate([jnp.zeros((1,), dtype), t_star + eta])

    def row(t_at, l_at, t_from, l_from):
        a_at = lookup(channel_table, centre(t_at), order=cfg.lookup_order)
        a_from = lookup(channel_table, centre(t_from), order=cfg.lookup_order)
        ratio = jnp.exp(l_at - l_from)
        n = jnp.concatenate(
            [a_at - ratio[:, None] * a_from, (base * (1.0 - ratio))[:, None]], axis=1
        )
        return n * jnp.exp(-l_at)[:, None]  # relative residuals, as the event rows

    rows, weights = [], []
    for g_pol in (1.0, -1.0):
        exc = jnp.where(live, g_pol * (log_col - r_g), _NEG)
        ex_max = seg_max(exc)
        arg = seg_arg(exc, ex_max)
        ok = valid & (ends != g_pol) & (arg >= 0)
        w = jnp.where(ok, jnp.exp(_log_sig((ex_max - thr) / scfg.smoothing)), 0.0)
        jg = jnp.clip(arg, 0, n1 - 1)
        t_g, l_g = t_grid[jg], log_col[jg]
        rows.append(row(t_g, l_g, t_ref_row, r_int))
        weights.append(w)
        # Partner: first grid point after the extremum, same gap, back past r_i.
        back = (j > jg[iid]) & (g_pol * (log_col - r_g) <= 0.0)
        jp = jax.ops.segment_min(jnp.where(back, j, n1), iid, num_segments=segs)
        has = jp < n1
        jp = jnp.clip(jp, 0, n1 - 1)
        t_from = t_g + eta
        rows.append(row(t_grid[jp], log_col[jp], t_from, jax.vmap(level)(t_from)))
        weights.append(jnp.where(has, w, 0.0))
    r_all = jnp.concatenate(rows)
    w_all = jnp.concatenate(weights)
    smooth_count = count_rows + jnp.sum(w_all)
    if not scfg.weighted_rows:
        return q_mat, q_vec, smooth_count
    gram = (r_all * w_all[:, None]).T @ r_all
    m = q_mat.shape[0]
    return q_mat + gram[:m, :m], q_vec + gram[:m, m], smooth_count
