"""Events → cube: group pixels, assemble each pixel's QP, solve, write back.

Work is proportional to each pixel's own event count (buckets of padded lengths 16, 32,
…), pixels without events cost no solve, and each bucket chunk is processed with
`lax.map` over sub-batches so the per-pixel matrices stay in cache and memory stays
bounded by the chunk.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P
from tqdm.auto import tqdm

from .._base import call_exported, check_fits, readonly, shard, use_numba
from .._model import Calibration, EventStream, Rig, band_table
from . import _solvers
from ._deblur import deblur_cube, deblur_cube_device
from ._fused import FusedProblem, fused_supported, solve_fused
from ._pixels import (
    DeviceLists,
    PixelEvents,
    bucket_plan,
    bucket_sizes,
    group_pixels,
    pixel_lists,
)
from ._problem import (
    ProblemConfig,
    dark_rows,
    lit_interval_us,
    pixel_system,
    spectral_prior_matrix,
    system_from_rows,
)
from ._sweep_speed import (
    IDEAL_NOISE,
    SPEED_BOUND,
    estimate_speeds,
    warp_lists,
)
from ._sweep_speed import candidates as speed_candidates

__all__ = ["SolverSpec", "SOLVERS", "reconstruct", "ReconstructionInfo", "solver_spec"]


@dataclasses.dataclass(frozen=True)
class SolverSpec:
    """A named QP solver with its static budget (hashable: part of the jit key)."""

    name: str
    iters: int = 0
    tol: float = 0.0

    def solve(self, q_mat, q_vec, x0):
        if self.name == "apg":
            return _solvers.apg(q_mat, q_vec, x0, iters=self.iters)
        if self.name == "unconstrained":
            return _solvers.unconstrained(q_mat, q_vec)
        if self.name in ("boxcdqp", "boxosqp"):
            from . import _jaxopt

            fn = _jaxopt.boxcdqp if self.name == "boxcdqp" else _jaxopt.boxosqp
            kw = {}
            if self.iters:
                kw["maxiter"] = self.iters
            if self.tol:
                kw["tol"] = self.tol
            return fn(q_mat, q_vec, x0 if self.name == "boxcdqp" else None, **kw)
        raise ValueError(f"unknown solver {self.name!r}")


#: Solver names of the CLI and their default budgets. `auto` is chosen from the
#: speed-vs-error study (README): the fastest solver within 0.1° SAM of the reference.
SOLVERS: dict[str, SolverSpec] = {
    "active-set": SolverSpec("active-set", iters=48, tol=1e-6),
    "apg": SolverSpec("apg", iters=1000),
    "boxcdqp": SolverSpec("boxcdqp", iters=500, tol=1e-6),
    "boxosqp": SolverSpec("boxosqp", iters=4000, tol=1e-5),
    "svd": SolverSpec("svd"),
    "unconstrained": SolverSpec("unconstrained"),
}
AUTO = "active-set"


def solver_spec(name: str | SolverSpec) -> SolverSpec:
    if isinstance(name, SolverSpec):
        return name
    if name == "auto":
        name = AUTO
    if name not in SOLVERS:
        raise ValueError(
            f"unknown solver {name!r}; choose from auto, {', '.join(SOLVERS)}"
        )
    return SOLVERS[name]


@dataclasses.dataclass(frozen=True)
class ReconstructionInfo:
    """Per-pixel diagnostics of a reconstruction (all shaped `(H, W)`)."""

    events: np.ndarray  # event count per pixel
    kkt: np.ndarray  # KKT residual of the returned solution (NaN: no solve)
    solved: np.ndarray  # True where a QP was solved
    t_start_us: int
    sweeps: int
    hot_pixels: np.ndarray | None = None  # hot pixels (filled from neighbours)
    dropped_events: int = 0  # events outside the lit intervals or of hot pixels
    sweeps_left_out: int = 0  # sweeps with events not used (`select_sweeps`)
    events_left_out: int = 0  # the events of those sweeps
    first_sweep: int = 0  # sweeps between the asked start and the first one used
    stray_events: int = 0  # events inside lit intervals removed (`repair_strays`)
    # Each sweep's mirror-speed factor the events were read with (None: the rig's
    # nominal speed; `reconstruct(sweep_speed=...)`, :mod:`._sweep_speed`).
    sweep_speed: np.ndarray | None = None


MAX_WHOLE_SWEEPS = 32
LOW_SWEEP_REL = 0.5


def select_sweeps(
    t_us: np.ndarray,
    t_start_us: int,
    period_us: float,
    *,
    rel: float = LOW_SWEEP_REL,
    max_sweeps: int = MAX_WHOLE_SWEEPS,
) -> tuple[int, int, int]:
    """The sweeps of a whole-file reconstruction: the longest run of consecutive lit
    sweeps.

    The per-pixel model expects the band to make events in every sweep it spans (its
    anti-drift rows pull a pixel to the baseline where no event says otherwise), so a
    sweep without events — light off at the start, a `t_start_us` one period early, a
    stray timestamp far away, a partial last sweep — must not be in it. A sweep is
    *lit* when it holds at least `rel` × the median events of the sweeps that hold
    any; the answer uses the longest run of consecutive lit sweeps (the earliest of
    equals), at most `max_sweeps` of it (each sweep adds rows to every pixel's
    system). Memory follows the number of events, not the time span.

    **Returns:** `(first, sweeps, left_out)` — the run's first sweep (counted from
    `t_start_us`), its length in sweeps, and the number of sweeps with events that
    were left out.
    """
    if t_us.size == 0:
        return 0, 1, 0

    def sweep_of(t):  # the sweep index of a time (non-decreasing in t)
        return int(np.floor((t - t_start_us) / float(period_us)))

    # Sweep by sweep: where the next sweep with events starts, by a binary search on
    # the sorted times (not the sweep index of every event; the empty sweeps between
    # are skipped, so a stray timestamp far away costs nothing).
    n_ev = t_us.size
    ks, counts = [], []
    i = 0
    while i < n_ev:
        k = sweep_of(t_us[i])
        lo, hi = i + 1, n_ev
        while lo < hi:
            mid = (lo + hi) // 2
            if sweep_of(t_us[mid]) <= k:
                lo = mid + 1
            else:
                hi = mid
        ks.append(k)
        counts.append(lo - i)
        i = lo
    ks, counts = np.asarray(ks, np.int64), np.asarray(counts)
    lit = counts >= rel * np.median(counts)
    best = (0, -1)  # (length, first index into ks)
    i = 0
    while i < ks.size:
        if not lit[i]:
            i += 1
            continue
        j = i
        while j + 1 < ks.size and lit[j + 1] and ks[j + 1] == ks[j] + 1:
            j += 1
        if j - i + 1 > best[0]:
            best = (j - i + 1, i)
        i = j + 1
    n, first = best
    n = min(n, max_sweeps)
    return int(ks[first]), n, int(ks.size - n)


#: Pixels per chunk and per `lax.map` step on a CPU and on an accelerator (GPU/TPU).
#: CPU: 128 pixels' matrices (~3 MB in float32) stay in the cache; chunks of 2048
#: bound the padded work of the last chunk of a bucket. GPU: one vmapped step of
#: 2^17 pixels fills the device (a 1280x720 sweep is ~7 chunks); memory ~30 kB per
#: pixel and slot bucket, a few GB (experiments/bench_gpu.py).
CPU_BATCH = (2048, 128)
ACCELERATOR_BATCH = (1 << 17, 1 << 17)


def batch_sizes(
    chunk_pixels: int | None, sub_batch: int | None, mesh=None
) -> tuple[int, int]:
    """`(chunk_pixels, sub_batch)` with `None` replaced by the default of the devices
    that will run the solve (the mesh's, else JAX's default backend)."""
    on_cpu = shard.device_platform(mesh) == "cpu"
    chunk, sub = CPU_BATCH if on_cpu else ACCELERATOR_BATCH
    chunk = chunk if chunk_pixels is None else int(chunk_pixels)
    sub = min(sub, chunk) if sub_batch is None else int(sub_batch)
    if chunk < 1 or sub < 1:
        raise ValueError("chunk_pixels and sub_batch must be >= 1")
    return chunk, sub


def channel_table(rig: Rig):
    """The reconstruction's A(λc) table, `band_table(rig).channels(sub)`, built by one
    compiled call (keyed by the FWHM, which sets the table's static range) instead of
    ~40 operations run one by one, each a compilation or cache read of its own at
    every process start (~0.4 s of `evhsi reconstruct`). Equal to the eager table to
    float32 rounding (3e-7 of a 0.05 peak)."""
    return _channel_table(rig, float(rig.fwhm_nm))


@functools.partial(jax.jit, static_argnums=1)
def _channel_table(rig: Rig, bound: float):
    return band_table(rig, fwhm_bound_nm=bound).channels(rig.grid.sub)


@eqx.filter_jit
def _rig_geometry(rig: Rig, width: int) -> dict:
    """The rig's period and each column's lit interval (:func:`lit_interval_us`) in
    one compiled call: evaluated op by op, each scalar operation is a compilation (a
    cache read) of its own at every start of a process."""
    arrive, leave = lit_interval_us(rig, rig.column_offsets(width))
    return {"period_us": rig.period_us, "arrive": arrive, "leave": leave}


def _no_event_answer(rig: Rig, m: int) -> float:
    """Reflectance for a pixel without events: half the largest flat reflectance that
    stays below the ON threshold (a white-normalised peak of ρ gives ρ)."""
    base = float(rig.baseline_level)
    return 0.5 * base * math.expm1(float(rig.threshold_on))


#: Matrix products of the per-pixel problems in full float32 (GPUs otherwise round
#: float32 products to TF32's 10-bit mantissa: measured on an H100, only 77 % of a
#: 1280x720 ColorChecker's pixels stayed within 0.1° of a float64 solve; CPUs are
#: unaffected).
MATMUL_PRECISION = "highest"


def _keep_moved(cfg: ProblemConfig, more, old, new):
    """One Gauss–Newton pass of the photoreceptor model for the pixels in `more`
    (`(B,)` bool): `(rows, x, kkt)` from `new` where `more`, else from `old`, and
    the pixels to take the next pass — those this pass moved by more than
    `cfg.lowpass_tol` (as the fused kernel: ‖Δx‖² > tol² ‖x‖²)."""
    pick = lambda a, b: jnp.where(  # noqa: E731
        more.reshape(more.shape + (1,) * (jnp.ndim(a) - 1)), b, a
    )
    rows, x, kkt = jax.tree.map(pick, old, new)
    d = new[1] - old[1]
    moved = jnp.sum(d * d, axis=-1) > cfg.lowpass_tol**2 * jnp.sum(new[1] ** 2, axis=-1)
    return rows, x, kkt, more & moved


@eqx.filter_jit
def _solve_chunk(
    rig,
    table,
    cfg: ProblemConfig,
    spec: SolverSpec,
    sub: int,
    px: PixelEvents,
    sweeps: int,
    noise=None,
):
    """Assemble and solve a chunk of pixels `px` (a batch of `n`); returns x (n, M)
    and KKT residuals. `noise` is the sensor noise model of :func:`pixel_system` (then
    the robust reweighting of `cfg.robust_steps` runs)."""

    def system(one):
        return pixel_system(rig, table, cfg, one, sweeps)[:2]

    def solve_qp(q_mat, q_vec):
        if spec.name == "active-set":
            x, kkt, _ = _solvers.active_set_batch(
                q_mat, q_vec, tol=spec.tol, max_iters=spec.iters
            )
            return x, kkt
        x = jax.vmap(lambda a, b: spec.solve(a, b, None))(q_mat, q_vec)
        return x, jax.vmap(_solvers.kkt_residual)(q_mat, q_vec, x)

    def robust_batch(args):
        rows = _batch_rows(rig, table, cfg, args, sweeps, noise)
        q_mat, q_vec, _ = jax.vmap(lambda r: system_from_rows(cfg, r))(rows)
        x, kkt = solve_qp(q_mat, q_vec)
        more = jnp.ones(x.shape[0], bool)  # the pixels that take the next pass
        for _ in range(cfg.lowpass_passes):
            # A photoreceptor low-pass: relinearise its model at the current answer
            # (a pixel whose last pass moved it by ≤ lowpass_tol keeps its answer).
            def relinearise(rows=rows, x=x, kkt=kkt, more=more):
                new = _batch_rows(rig, table, cfg, args, sweeps, noise, x)
                qm, qv, _ = jax.vmap(lambda r: system_from_rows(cfg, r))(new)
                x_new, kkt_new = solve_qp(qm, qv)
                return _keep_moved(cfg, more, (rows, x, kkt), (new, x_new, kkt_new))

            rows, x, kkt, more = jax.lax.cond(
                (noise[2] > 0) & jnp.any(more),
                relinearise,
                lambda r=rows, x=x, k=kkt: (r, x, k, jnp.zeros_like(more)),
            )
        for _ in range(cfg.robust_steps):
            u, any_big = _huber_weights(cfg, rows, args.mask, x)

            def resolve(u=u):
                qm, qv, _ = jax.vmap(lambda r, w: system_from_rows(cfg, r, w))(rows, u)
                return solve_qp(qm, qv)

            x, kkt = jax.lax.cond(any_big, resolve, lambda x=x, k=kkt: (x, k))
        return x, kkt

    def one_batch(args):
        if noise is not None and spec.name not in ("svd", "unconstrained"):
            return robust_batch(args)
        q_mat, q_vec = jax.vmap(system)(args)
        if spec.name == "active-set":
            x, kkt, _ = _solvers.active_set_batch(
                q_mat, q_vec, tol=spec.tol, max_iters=spec.iters
            )
            return x, kkt
        if spec.name == "svd":
            gram = jax.vmap(lambda one: _augmented_gram(rig, table, cfg, one, sweeps))(
                args
            )
            x = jax.vmap(_solvers.svd_nullvector)(gram)
        else:
            x = jax.vmap(lambda a, b: spec.solve(a, b, None))(q_mat, q_vec)
        return x, jax.vmap(_solvers.kkt_residual)(q_mat, q_vec, x)

    n = px.t_us.shape[0]
    xs = jax.tree.map(lambda a: a.reshape((n // sub, sub) + a.shape[1:]), px)
    with jax.default_matmul_precision(MATMUL_PRECISION):
        x, kkt = jax.lax.map(one_batch, xs)
    return x.reshape(n, -1), kkt.reshape(n)


def _huber_weights(cfg: ProblemConfig, rows, mask, x):
    """One step of iteratively reweighted least squares with Huber weights: rows whose
    residual exceeds c standard deviations (a noise event, a missed or extra
    crossing) count linearly instead of quadratically, beyond `robust_reject` not at
    all. Residuals are in standard deviations of their rows, measured against the
    larger of that and the pixel's own typical residual (1.4826 × median |z| over its
    events), so a model error shared by all its rows is not an outlier. Returns the
    event rows' weights `(n, k)` and whether any row of the batch is far out."""
    z = _standard_residuals(rows, x)
    med = jnp.nanmedian(jnp.where(mask, jnp.abs(z), jnp.nan), axis=1)
    scale = jnp.maximum(1.4826 * jnp.nan_to_num(med), 1.0)
    z = z / scale[:, None]
    big = (jnp.abs(z) > cfg.robust_c) & mask
    u = jnp.where(big, jnp.sqrt(cfg.robust_c / jnp.abs(z)), 1.0)
    u = jnp.where(jnp.abs(z) > cfg.robust_reject, 0.0, u)
    return u, jnp.any(big)


def _standard_residuals(rows, x):
    """The event rows' residuals at the answers `x` `(n, M)`, in standard deviations
    of their rows, `(n, k)`."""
    xa = jnp.concatenate([x, jnp.ones_like(x[:, :1])], axis=1)
    return jnp.einsum("bkm,bm->bk", rows.events, xa) / rows.sigma


def _batch_rows(rig, table, cfg, px: PixelEvents, sweeps: int, noise, x0=None):
    """The weighted rows of a batch of pixels (:func:`pixel_system` with
    `return_rows`, vmapped; with `x0` `(n, M)`, the photoreceptor model linearised
    there)."""

    def rows_of(one, x=None):
        return pixel_system(
            rig, table, cfg, one, sweeps, noise=noise, return_rows=True, x0=x
        )

    return jax.vmap(rows_of)(px) if x0 is None else jax.vmap(rows_of)(px, x0)


@eqx.filter_jit
def _chunk_rows(rig, table, cfg: ProblemConfig, px: PixelEvents, sweeps: int,
                noise=None, x0=None):  # fmt: skip
    """A chunk's rows (:func:`_batch_rows`) and each pixel's number of events, for
    the CUDA kernel."""
    with jax.default_matmul_precision(MATMUL_PRECISION):
        rows = _batch_rows(rig, table, cfg, px, sweeps, noise, x0)
    if rows.dark is not None:  # the kernel takes rows: the dark prior's too
        rows = rows._replace(
            drift=jnp.concatenate([rows.drift, dark_rows(rows.dark)], axis=1),
            dark=None,
        )
    return rows, jnp.sum(px.mask, axis=1, dtype=jnp.int32)


@eqx.filter_jit
def _chunk_huber(cfg: ProblemConfig, rows, mask, x):
    with jax.default_matmul_precision(MATMUL_PRECISION):
        return _huber_weights(cfg, rows, mask, x)


def _solve_chunk_cuda(rig, table, cfg, spec, sub, px, sweeps, noise=None, first=None):
    """:func:`_solve_chunk` with the CUDA kernel (`backend="cuda"`): JAX forms the
    rows, the kernel (:mod:`._cuda_kernel`) each pixel's Gram matrix, priors and box
    QP in the GPU's on-chip memory; the photoreceptor passes (their rows by the
    kernel of :mod:`._cuda_lowpass`) and the robust reweighting of the noise model
    run as in :func:`_solve_chunk`, each solve through the kernel. `sub` is unused
    (the kernel takes the whole chunk); `first`: the chunk's first rows and counts
    (`_chunk_rows`), when the caller has dispatched them already."""
    from . import _cuda_kernel as ck

    m = table.values.shape[1]
    prior = spectral_prior_matrix(m, cfg.m_start_frac, cfg.spec_kind)

    def solve(rows, n, u=None):
        jax.block_until_ready((rows, n, u))
        x, kkt, _ = ck.solve_rows(
            rows, n, prior, cfg.ridge, spec.tol, spec.iters, ev_w=u
        )  # fmt: skip
        return ck.to_jax(x), ck.to_jax(kkt)

    rows, n = _chunk_rows(rig, table, cfg, px, sweeps, noise) if first is None else first
    x, kkt = solve(rows, n)
    if noise is None:
        return x, kkt
    if float(noise[2]) > 0:
        more = jnp.ones(x.shape[0], bool)  # the pixels that take the next pass
        for p in range(cfg.lowpass_passes):
            # After the first pass only the pixels it moved take another: to both
            # kernels the others are padding slots (skipped: no rows formed, no
            # solve), and _keep_moved keeps their answers.
            n_p = n if p == 0 else jnp.where(more, n, 0)
            if cfg.lookup_order == 1:  # the photoreceptor rows by a kernel too
                new = rows._replace(events=_lowpass_rows_cuda(rig, table, noise,
                                                              sweeps, px, n_p, rows, x))
            else:  # (the counts are the chunk's mask's, the same as `n`)
                new, _ = _chunk_rows(rig, table, cfg, px, sweeps, noise, x)
            rows, x, kkt, more = _keep_moved(
                cfg, more, (rows, x, kkt), (new, *solve(new, n_p))
            )
            if not bool(jnp.any(more)):
                break
    for _ in range(cfg.robust_steps):
        u, any_big = _chunk_huber(cfg, rows, px.mask, x)
        if bool(any_big):
            x, kkt = solve(rows, n, u)
    return x, kkt


def _lowpass_rows_cuda(rig, table, noise, sweeps, px, n, rows, x):
    """The photoreceptor model's event rows linearised at `x` (JAX `(B, M)`) by the
    kernel of :mod:`._cuda_lowpass` — `_chunk_rows(..., x0=x)`'s `events` without
    JAX's `(B, grid, M+1)` scan — as a JAX array. It runs on numba's stream: the
    next kernel launch there sees it; the solve after it waits for both."""
    from . import _cuda_kernel as ck
    from . import _cuda_lowpass as cl

    par, g_n = cl.lowpass_params(rig, table, noise, sweeps)
    jax.block_until_ready((px, n, rows.log_weight, x, table.values))
    out = cl.lowpass_rows(px, n, rows.log_weight, x, table.values, par, g_n)
    return ck.to_jax(out)


def _solve_chunks_cuda_noise(rig, table, cfg, spec, chunks, sweeps, noise):
    """The chunks of a reconstruction with a noise model through the CUDA kernels
    (:func:`_solve_chunk_cuda`), each chunk's first rows dispatched to JAX before
    the chunk before it is solved, so that JAX forms them while the kernels run.
    `chunks` yields `(pixel, pixel_device, px)`; yields each with its `(x, kkt)`."""

    def solved(chunk, first):
        return (*chunk, *_solve_chunk_cuda(
            rig, table, cfg, spec, 0, chunk[2], sweeps, noise, first
        ))  # fmt: skip

    pending = None
    for chunk in chunks:
        first = _chunk_rows(rig, table, cfg, chunk[2], sweeps, noise)  # dispatched
        if pending is not None:
            yield solved(*pending)
        pending = (chunk, first)
    if pending is not None:
        yield solved(*pending)


def _solve_chunks_cuda(rig, table, cfg, spec, chunks, sweeps):
    """The chunks of a reconstruction without noise model through the CUDA kernel,
    each chunk's rows formed by JAX while the kernel solves the one before:
    `chunks` yields `(pixel, pixel_device, px)` as `reconstruct` makes them; yields
    each with its `(x, kkt)` (JAX arrays), in order — :func:`_solve_chunk_cuda`'s
    answers. The kernel runs on numba's stream, JAX on its own, so the host orders
    them: it waits for a chunk's rows before launching the kernel on them, and for
    the kernel before JAX reads its answers; a chunk's rows stay referenced (in
    `pending`) until then (JAX would reuse their memory), and numba frees nothing
    meanwhile (a free waits for the whole device)."""
    from . import _cuda_kernel as ck

    m = table.values.shape[1]
    prior = spectral_prior_matrix(m, cfg.m_start_frac, cfg.spec_kind)
    pending = None  # (chunk, its answers on numba's side, its rows)

    def answers(chunk, out, _rows):
        ck.synchronize()
        return (*chunk, ck.to_jax(out[0]), ck.to_jax(out[1]))

    with ck.deferred_frees():
        for chunk in chunks:
            rows, n = _chunk_rows(rig, table, cfg, chunk[2], sweeps)  # (dispatched)
            if pending is not None:
                yield answers(*pending)
            jax.block_until_ready((rows, n))
            out = ck.solve_rows(
                rows, n, prior, cfg.ridge, spec.tol, spec.iters, wait=False
            )  # fmt: skip
            pending = (chunk, out, (rows, n))
        if pending is not None:
            yield answers(*pending)


def _solve_chunk_stored(rig, table, cfg, spec, sub, px, sweeps, noise=None):
    """:func:`_solve_chunk` through the stored traced program of its shapes when the
    compilation cache is on (`call_exported`: a second process skips tracing)."""
    args = (rig, table, cfg, spec, sub, px, sweeps, noise)
    return call_exported("reconstruct_chunk", _solve_chunk, args)


@eqx.filter_jit
def _solve_robust(
    rig,
    table,
    cfg: ProblemConfig,
    iters: int,
    px: PixelEvents,
    sweeps: int,
    noise=None,
):
    """The exact active-set solution pixel by pixel (`lax.map`), with Cholesky
    factorisations retried under a rounding-level shift where they fail
    (:func:`._solvers.cho_factor`). For the rare pixels whose batched solve came out
    non-finite: float32 systems that are indefinite by rounding (few events, weak
    priors). Same arguments as :func:`_solve_chunk`, minus the solver and sub-batch."""

    def one(args):
        q_mat, q_vec = pixel_system(rig, table, cfg, args, sweeps, noise=noise)[:2]
        x = _solvers.active_set(q_mat, q_vec, iters=iters, robust=True)
        return x, _solvers.kkt_residual(q_mat, q_vec, x)

    with jax.default_matmul_precision(MATMUL_PRECISION):
        return jax.lax.map(one, px)


def _device_pixels(t_us, polarity, mask, pix, column, d, offsets, thr_on, thr_off,
                   dtype) -> PixelEvents:  # fmt: skip
    """The :class:`PixelEvents` of a batch (padded slots `(n, k)`, flat pixel indices
    `pix`, columns, clock shifts `d`). Converted on the host and put on the device as
    they are: `jnp.asarray` of a NumPy array, or a dtype conversion there, is a
    compiled operation per shape (a cache read at every start of a process)."""
    return PixelEvents(
        *jax.device_put(
            (
                np.where(mask, t_us + d[:, None], 0.0).astype(dtype),
                polarity.astype(np.int32),
                mask,
                offsets[column].astype(dtype),
                thr_on[pix].astype(dtype),
                thr_off[pix].astype(dtype),
                (-d).astype(dtype),
            )
        )
    )


def _solve_robust_at(rig, table, cfg, spec, px, idx, sweeps, noise):
    """:func:`_solve_robust` for the pixels `idx` of the batch `px`, padded to a power
    of two (few compiled sizes); NumPy `(x, kkt)` of the `idx.size` pixels."""
    n_pad = 1 << int(math.ceil(math.log2(idx.size)))
    sel = np.concatenate([idx, np.full(n_pad - idx.size, idx[0])])
    xr, kr = _solve_robust(
        rig, table, cfg, max(spec.iters, 48), jax.tree.map(lambda a: a[sel], px),
        sweeps, noise,
    )  # fmt: skip
    return np.asarray(xr)[: idx.size], np.asarray(kr)[: idx.size]


def _augmented_gram(rig, table, cfg, px: PixelEvents, sweeps):
    """$\\hat N^T \\hat N$ of the event rows alone (the paper's SVD system)."""
    bare = dataclasses.replace(cfg, alpha_int=0.0, alpha_spec=0.0, ridge=0.0)
    q_mat, q_vec, _ = pixel_system(rig, table, bare, px, sweeps, return_gram=True)
    return q_mat


#: Below these, a sensor counts as ideal: its rows are as accurate as the ideal
#: simulator's after calibration (RMS residual ~0.002 thresholds = 3e-4 log), and the
#: ideal problem (every event an exact constraint) is the more accurate one.
MATERIAL_THRESHOLD_NOISE = 0.002  # log units
MATERIAL_JITTER_US = 1.0
#: Background activity from this rate on puts noise events inside the lit intervals
#: (~1 % of the pixels per sweep at 0.5 Hz): the robust reweighting is then needed.
MATERIAL_BACKGROUND_HZ = 0.05


#: A sensor with a noise model but no photoreceptor cut-off (none measured, or a fast
#: one) is solved with the photoreceptor passes of an instantaneous photoreceptor of
#: this cut-off (d_w = 0.16 µs, far below the rig's 28 µs time step): their rows are
#: in log units, where per-crossing threshold noise is additive. The first solve's
#: linear rows carry it as (e^ε − 1) e^{σC} I(ρ), whose expected square adds
#: σ_C² Σ (e^{σC} I(ρ_k))² to the objective and pulls every intensity down (threshold
#: noise 0.01 alone, true maps: 3.11° from 16 sweeps with the linear rows, 2.30° with
#: the passes; README Limitations, "Threshold noise leaves a bias").
LOG_MODEL_HZ = 1e6

#: Sweeps up to which the JAX path's photoreceptor passes keep the full sub-batch;
#: a longer recording's sub-batch shrinks in proportion (`reconstruct`).
LOWPASS_SUB_SWEEPS = 4


def solve_noise(noise: np.ndarray | None, cfg: ProblemConfig) -> np.ndarray | None:
    """The noise model the solve uses: :func:`noise_model`'s, with the instantaneous
    photoreceptor of `LOG_MODEL_HZ` where it has none, material threshold noise or
    timestamp jitter, and `cfg` asks for passes (background activity alone leaves
    the rows unbiased: no passes)."""
    if noise is None or noise[2] > 0 or cfg.lowpass_passes == 0:
        return noise
    if noise[0] < MATERIAL_THRESHOLD_NOISE and noise[1] < MATERIAL_JITTER_US:
        return noise
    return np.array([noise[0], noise[1], white_delay_us(LOG_MODEL_HZ)])


def white_delay_us(cutoff_hz: float) -> float:
    """$d_w = 1/(2π f_c)$ in µs: a photoreceptor's time constant at a white pixel's
    peak intensity, from its cut-off (Hz)."""
    return 1e6 / (2 * np.pi * cutoff_hz)


def noise_model(rig: Rig) -> np.ndarray | None:
    """The sensor noise model `[σ_C, σ_t, d_w]` of :func:`pixel_system` from the rig's
    sensor keys, or `None` for a sensor that is ideal within what a calibration can
    tell (σ_C < 0.002 log, σ_t < 1 µs, no photoreceptor low-pass and background
    activity below 0.05 Hz per pixel)."""
    fx = rig.effects.floats()
    d_w = white_delay_us(fx.photoreceptor_hz) if fx.photoreceptor_hz > 0 else 0.0
    material = (
        fx.threshold_noise >= MATERIAL_THRESHOLD_NOISE
        or fx.timestamp_jitter_us >= MATERIAL_JITTER_US
        or d_w > 0
        or rig.noise_rate_hz >= MATERIAL_BACKGROUND_HZ
    )
    if not material:
        return None
    return np.array([fx.threshold_noise, fx.timestamp_jitter_us, d_w])


def reconstruct(
    events: EventStream,
    calibration: Calibration | Rig,
    *,
    solver: str | SolverSpec = "auto",
    config: ProblemConfig | None = None,
    threshold_on_map: np.ndarray | None = None,
    threshold_off_map: np.ndarray | None = None,
    t_start_us: int | None = None,
    reference_us: np.ndarray | None = None,
    chunk_pixels: int | None = None,
    sub_batch: int | None = None,
    progress: bool = False,
    return_info: bool = False,
    mesh=None,
    deblur: bool | None = None,
    backend: str = "auto",
    threads: int | None = None,
    sweep_speed="auto",
):
    """Reconstruct a reflectance cube from an event recording of a static scene.

    **Arguments:**

    - `events`: the recording (one or more sweeps of a static scene).
    - `calibration`: a :class:`Calibration` (:func:`evhsi_jax.load_calibration`): its
      rig, per-pixel thresholds, hot-pixel map and sensor noise are all used. A bare
      :class:`Rig` means global thresholds and the noise its sensor keys give (none by
      default; `Rig.load` refuses a file that names per-pixel maps: load it with
      `load_calibration`).
    - `solver`: a name from `SOLVERS`, `"auto"`, or a :class:`SolverSpec`.
    - `config`: the per-pixel problem's weights (:class:`ProblemConfig`). When the
      calibration measured background activity, the pixels that fit their events
      badly are then searched for one or two stray events, which are removed
      (`config.stray_z`, :func:`repair_strays`; the info's `stray_events`).
    - `threshold_on_map`, `threshold_off_map`: optional per-pixel thresholds `(H, W)`
      (log units) from a calibration; default the rig's global values.
    - `t_start_us`: time at which the recording's first sweep starts (sweep phase 0);
      default the first trigger, else 0. Sweeps without events (and partial ones)
      are left out: the longest run of lit sweeps is used, at most
      `MAX_WHOLE_SWEEPS` (:func:`select_sweeps`; the info says how many were not).
    - `reference_us`: optional `(H, W)` times (µs, same clock as the events; NaN for
      none) at which each pixel's reference level was last set before `t_start_us` —
      the release $τ + η$ after its last earlier event. The pixel's first event then
      refers to the intensity at that time (under the spectrum being solved for)
      instead of the baseline c' at `t_start_us`: what a recording cut out of a longer
      one needs (:func:`evhsi_jax.reconstruct_sweeps`). Default: all at `t_start_us`.
    - `chunk_pixels`: pixels per compiled chunk (memory ∝ chunk × events per pixel;
      this and `sub_batch` are the JAX backend's: the fused one works pixel by pixel).
    - `sub_batch`: pixels per `lax.map` step inside a chunk.
      Defaults by the device kind (:func:`batch_sizes`): 2048 / 128 on a CPU (each
      step's matrices stay in cache), 131072 / 131072 on a GPU (one step per chunk:
      a GPU needs tens of thousands of pixels in flight). On an accelerator the
      events are sorted by pixel and cut into the chunks there (`DEVICE_GROUPING`).
    - `progress`: show a progress bar.
    - `return_info`: also return a :class:`ReconstructionInfo`.
    - `deblur`: undo the optics' blur, a Gaussian PSF of the rig's `psf_sigma_px`
      (which `calibrate` measures), by Wiener deconvolution of each channel
      (:func:`evhsi_jax.reconstruction.deblur_cube`). Default (`None`): when that σ
      is > 0, i.e. when the calibration measured a blur (README "Real sensors" has
      what it gains and costs, `experiments/deblur.py`).
    - `backend`: `"jax"` (each chunk of pixels assembled and solved by a compiled JAX
      kernel: any solver, noise model and device), `"fused"` (the CPU kernel of
      :mod:`._fused`: each pixel's system formed from band segments and solved where
      it is formed, in float64, on `threads` cores; the active-set solver with the
      linear lookup, ideal or noise-aware — a `ValueError` says why otherwise),
      `"cuda"` (JAX forms each chunk's rows on a CUDA GPU, the kernel of
      :mod:`._cuda_kernel` their Gram matrices and box QPs in the GPU's on-chip
      memory, float32, each chunk's rows formed while the kernel solves the one
      before; the photoreceptor pass's rows by the kernel of
      :mod:`._cuda_lowpass`; needs numba's CUDA target, the active-set solver and
      a float32 rig;
      on an H100 a warm whole sweep 1.34× faster than jax; the compiled kernel is
      kept in numba's disk cache) or `"auto"` (default): fused where it applies and the solve
      would run on a CPU, else JAX; on a CUDA GPU cuda for calls of at least
      `AUTO_CUDA_MIN_PIXELS` pixel·sweeps (2^19), after its self-check.
      The fused cube is the float64 solve of the same events (within 0.01° SAM of the
      JAX path run in float64; float32 JAX and cuda differ from both by their
      rounding).
    - `threads`: worker threads of the fused backend (default: the usable cores).
    - `sweep_speed`: each sweep's mirror speed relative to the calibration's.
      `"auto"` (default): each sweep's factor measured from the recording (each
      sweep of :func:`evhsi_jax.reconstruct_sweeps` alone; in a recording of
      several, each with the sweep before it) when numba is there (the fused kernel
      solves the subsets, whatever the backend): a mirror whose speed varies by
      0.2 % from sweep to sweep otherwise costs a ColorChecker sweep ~1.3° SAM
      (:mod:`._sweep_speed`); `"off"`: the nominal speed; or the factors
      themselves, one per sweep used. The info's `sweep_speed` has the
      factors used (None: the nominal speed).
    - `mesh`: a `jax.sharding.Mesh` with a `"pixels"` axis
      (:func:`evhsi_jax.sharding.pixel_mesh`): each chunk's pixels are split over its devices,
      `chunk_pixels` per device, each with the same per-pixel kernel. A one-device
      mesh gives the plain run's cube bit for bit; on several CPU devices XLA compiles
      the kernel differently and the cube differs by float32 rounding (3e-5 on
      reflectance ~0.5 in tests/reconstruction/test_shard.py; solved pixels and event counts equal).
      Several CPU devices solve one pixel per sub-batch (see
      `evhsi_jax._base._shard.sub_batch_for`).

    **Returns:** the cube `(H, W, M)` float32 (and the info if asked). Never NaN: a
    pixel whose batched solve is non-finite (float32 rounding on a nearly singular
    system) is re-solved alone by the exact active-set method with shifted-retry
    factorisations; one still non-finite after that (or from `svd`/`unconstrained`)
    gets the no-event answer and KKT = inf.
    """
    if isinstance(calibration, Calibration):
        cal = calibration
    elif isinstance(calibration, Rig):  # (a rig never names maps: Rig.load refuses)
        cal = Calibration(calibration)
    else:
        raise TypeError("calibration must be a Calibration or a Rig")
    rig = cal.rig
    spec = solver_spec(solver)
    cfg = config or ProblemConfig()
    h, w = events.height, events.width
    cal.check_size(h, w)
    # The cube, its float64 work copies and the per-pixel bookkeeping.
    check_fits(
        float(h) * w * (16 * rig.channels + 64),
        f"a {h}x{w}x{rig.channels} reconstruction",
    )
    if threshold_on_map is None and cal.threshold_on is not None:
        threshold_on_map, threshold_off_map = cal.threshold_on, cal.threshold_off
    noise = noise_model(rig)
    m = rig.channels
    offsets_all = np.asarray(rig.column_offsets(w), np.float64)
    if t_start_us is None:
        t_start_us = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    if len(events) and int(events.t_us[0]) < t_start_us:
        raise ValueError(
            f"events start at {int(events.t_us[0])} µs, before the sweep start "
            f"{t_start_us} µs"
        )
    period = float(_rig_geometry(rig, w)["period_us"])
    n_all = len(events)
    first, sweeps, left_out = select_sweeps(events.t_us, t_start_us, period)
    if first or left_out:
        t_start_us = int(round(t_start_us + first * period))
        stop = int(math.ceil(t_start_us + sweeps * period))
        events = events.time_window(t_start_us, stop)
    speeds = _speed_setting(sweep_speed, sweeps)
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if threads is not None and int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    why_not = fused_supported(spec, cfg)
    if backend == "fused" and why_not is not None:
        raise ValueError(f"the fused backend cannot run this reconstruction: {why_not}")
    fused = backend == "fused" or (
        backend == "auto" and why_not is None and shard.device_platform(mesh) == "cpu"
    )
    chunk_pixels, sub_batch = batch_sizes(chunk_pixels, sub_batch, mesh)
    sub = max(1, min(sub_batch, chunk_pixels))
    solve, n_dev = _solve_chunk_stored, 1
    if _use_cuda(backend, fused, spec, cfg, rig, mesh, h * w * sweeps):
        solve = _solve_chunk_cuda
    noise_solve = solve_noise(noise, cfg)
    if (
        not fused
        and solve is not _solve_chunk_cuda
        and noise_solve is not None
        and noise_solve[2] > 0
        and cfg.lowpass_passes > 0
        and sweeps > LOWPASS_SUB_SWEEPS
    ):
        # The JAX path forms each pixel's photoreceptor grid (sweeps × samples per
        # sweep points × channels) for a whole sub-batch at once: keep that at the
        # size of LOWPASS_SUB_SWEEPS sweeps (~1.9 GB peak on a CPU at 4 sweeps).
        sub = max(1, sub * LOWPASS_SUB_SWEEPS // sweeps)
    if mesh is not None:
        solve, n_dev = functools.partial(solve_chunk_sharded, mesh), mesh.devices.size
        sub = shard.sub_batch_for(mesh, sub)
    chunk = sub * math.ceil(chunk_pixels / sub)
    keep, n_kept, hot, n_dropped = _screen_mask(
        events, rig, t_start_us, noise, sweeps, cal.hot_pixels
    )  # (screen_events; the kept events taken below where needed)
    noise = noise_solve
    # The mirror's speed of each sweep, measured from the recording (_sweep_speed).
    estimate = isinstance(speeds, str) and use_numba() and len(events) > 0
    # A bucket's last chunk is padded to sub × 2^j (small images and buckets pad
    # little); a bucket of fewer than a quarter chunk of pixels joins the next one
    # (one compiled shape less for a little padding).
    on_device = (
        not fused
        and mesh is None
        and (
            DEVICE_GROUPING is True
            or (DEVICE_GROUPING == "auto" and shard.device_platform(None) != "cpu")
        )
        and DeviceLists.fits(events, t_start_us)
    )
    plan, lists, batches = [], None, []
    lead = _reference_lead_us(reference_us, t_start_us, period, h, w)
    thr_on = (
        np.full(h * w, float(rig.threshold_on))
        if threshold_on_map is None
        else (_check_map(threshold_on_map, h, w, "threshold_on map"))
    )
    thr_off = (
        np.full(h * w, float(rig.threshold_off))
        if threshold_off_map is None
        else (_check_map(threshold_off_map, h, w, "threshold_off map"))
    )
    factors = speeds if isinstance(speeds, np.ndarray) else None
    if on_device:  # sorted and cut into batches where the solve runs
        lists = DeviceLists(events, t_start_us, keep)  # (the dropped sort last)
        counts = lists.counts
        plan = bucket_plan(counts, chunk, sub, chunk // 4)  # (mesh is None: n_dev 1)
        est_lists = None
        if estimate:  # (the host's lists of the pixels that may take part only)
            est_lists = _candidate_lists(events, keep, counts, sweeps, t_start_us)
    else:
        screened = events if keep is None else _take_kept(events, keep, n_kept)
        if fused or estimate or factors is not None:
            lists = est_lists = pixel_lists(screened, t_start_us)
            counts = lists[0]
    if estimate:
        factors = _estimate_speeds(
            rig, cfg, spec, w, offsets_all, sweeps, noise, est_lists, lead, thr_on,
            thr_off, period, threads,
        ).factors  # fmt: skip
    if factors is not None and not on_device:
        lists = warp_lists(lists, w, offsets_all, period, factors)
    if not on_device and not fused:
        batches, counts, _ = group_pixels(
            screened,
            t_start_us=t_start_us,
            chunk_pixels=chunk * n_dev,
            min_chunk=sub * n_dev,
            merge_below=chunk * n_dev // 4,
            lists=lists,
        )
    dtype = rig.fwhm_nm.dtype  # float32 or float64: the rig decides
    table = channel_table(rig)
    if solve is _solve_chunk_cuda:
        # The CUDA kernel works on each row's nonzero span: with the fused kernel's
        # trimmed bands, ~16 channels instead of a float32 Gaussian's ~28.
        table = table.trimmed()
    np_dtype = np.dtype(dtype)
    noise_j = None if noise is None else jax.device_put(np.asarray(noise, np_dtype))

    # The host's cube, unless the answers are placed into one on the device (`plan`).
    cube = kkt_all = None
    if not plan:
        cube = np.full((h * w, m), _no_event_answer(rig, m), np.float32)
        kkt_all = np.full(h * w, np.nan, np.float32)
    bar = tqdm(
        total=int(np.count_nonzero(counts)),
        disable=not progress,
        unit="px",
        desc=f"reconstruct ({spec.name})",
    )
    strays = 0
    repair = (
        noise is not None
        and cfg.stray_z > 0
        and rig.noise_rate_hz >= MATERIAL_BACKGROUND_HZ
        and spec.name not in ("svd", "unconstrained")
    )
    if fused:
        strays = _solve_fused_all(
            rig, table, cfg, spec, sweeps, lists, lead, offsets_all, thr_on, thr_off,
            cube, kkt_all, threads, bar.update, noise, repair,
        )  # fmt: skip

    def chunks():  # (flat pixel index per row, −1 for padding; its device copy when
        # the batch was gathered there, else None; the batch on the device)
        if plan:
            per_pixel = jax.device_put(
                tuple(a.astype(np_dtype) for a in (lead, offsets_all, thr_on, thr_off))
            )
            speed = None
            if factors is not None:
                speed = (jax.device_put(np.asarray(factors, np_dtype)), period)
            for sel, k, size in plan:
                yield lists.batch(sel, k, size, *per_pixel, np_dtype, speed)
        for b in batches:
            valid = b.pixel >= 0
            pix = np.where(valid, b.pixel, 0)
            # Carried references: shift each pixel's clock to start at its reference.
            d = np.where(valid, lead[pix], 0.0)
            yield b.pixel, None, _device_pixels(
                b.t_us, b.polarity, b.mask, pix, b.column, d, offsets_all, thr_on,
                thr_off, np_dtype,
            )  # fmt: skip

    # With the device's grouping the answers are placed into a cube on the device
    # too, and it comes back once (not chunk by chunk into the host's cube).
    held = None
    if plan:  # made there, not sent over (a 1280x720 cube is 270 MB)
        held = (
            jnp.full((h * w, m), _no_event_answer(rig, m), jnp.float32),
            jnp.full(h * w, jnp.nan, jnp.float32),
        )

    def solved():  # each chunk with its answers
        if solve is _solve_chunk_cuda:  # the next chunk's rows formed while the
            # kernels solve one
            if noise_j is None:
                yield from _solve_chunks_cuda(rig, table, cfg, spec, chunks(), sweeps)
            else:
                yield from _solve_chunks_cuda_noise(
                    rig, table, cfg, spec, chunks(), sweeps, noise_j
                )  # fmt: skip
            return
        for pixel, pix_dev, px in chunks():
            yield pixel, pix_dev, px, *solve(
                rig, table, cfg, spec, sub, px, sweeps, noise_j
            )  # fmt: skip

    # The JAX path's stray search needs each pixel's fit to its rows (the fused
    # kernel returns it with the answer).
    fit_all = np.full((h * w, 3), np.nan) if repair and not fused else None
    for pixel, pix_dev, px, x, kkt in solved():
        valid = pixel >= 0
        if fit_all is not None:
            fit = np.asarray(_chunk_fit(rig, table, cfg, px, sweeps, noise_j, x,
                                        float(noise[2]) > 0))  # fmt: skip
            fit_all[pixel[valid]] = fit[valid]
        if held is not None:
            if not bool(_any_failed(x, pix_dev)):
                held = _place(*held, pix_dev, x, kkt)
                bar.update(int(valid.sum()))
                continue
        x, kkt = np.asarray(x), np.asarray(kkt)
        failed = valid & ~np.all(np.isfinite(x), axis=1)
        if failed.any() and spec.name not in ("svd", "unconstrained"):
            # Rare: re-solve the chunk's failed pixels exactly, one by one.
            x, kkt = x.copy(), kkt.copy()  # device buffers are read-only
            idx = np.flatnonzero(failed)
            x[idx], kkt[idx] = _solve_robust_at(
                rig, table, cfg, spec, px, idx, sweeps, noise_j
            )
        if held is not None:
            held = _place(*held, pix_dev, *jax.device_put((x, kkt)))
        else:
            cube[pixel[valid]] = x[valid]
            kkt_all[pixel[valid]] = kkt[valid]
        bar.update(int(valid.sum()))
    bar.close()
    if fit_all is not None:
        sel = np.flatnonzero(counts)
        if np.any(np.nan_to_num(fit_all[sel, 0], nan=0.0) > cfg.stray_z):
            kept = screened if not on_device else (
                events if keep is None else _take_kept(events, keep, n_kept)
            )  # fmt: skip
            host_lists = pixel_lists(kept, t_start_us)
            if factors is not None:
                host_lists = warp_lists(host_lists, w, offsets_all, period, factors)
            solve_variants = functools.partial(
                _solve_variants_jax, rig, table,
                dataclasses.replace(cfg, robust_steps=0), spec, sub, chunk, sweeps,
                noise_j, host_lists, lead, offsets_all, thr_on, thr_off, np_dtype,
            )  # fmt: skip
            pix, xs, kkts, strays = repair_strays(
                solve_variants, sel, fit_all[sel], host_lists, cfg, period
            )
            if strays and held is not None:
                held = (
                    held[0].at[pix].set(jnp.asarray(xs, jnp.float32)),
                    held[1].at[pix].set(jnp.asarray(kkts, jnp.float32)),
                )
            elif strays:
                cube[pix], kkt_all[pix] = xs, kkts
    gain = None  # white-reference correction: times 1/gain (a product rounds alike
    # on every device; XLA's division need not be NumPy's to the last bit)
    if np.any(np.asarray(rig.channel_gain) != 1.0):
        gain = (1.0 / np.asarray(rig.channel_gain, np.float64)).astype(np.float32)
    psf = float(rig.effects.psf_sigma_px)
    deblurred = (psf > 0) if deblur is None else deblur
    clipped = hot_done = False
    if held is not None:  # finished on the device (gains, hot pixels' fill,
        # deblurring, clip), and the cube comes home once
        later = hot.any() or deblurred
        cube_d, kkt_d = _finish_on_device(
            *held, _no_event_answer(rig, m), gain,
            None if later else cfg.max_reflectance,
        )  # fmt: skip
        if hot.any():
            cube_d = _fill_from_neighbours_device(cube_d, hot, counts.reshape(h, w))
        if later:
            cube_d = deblur_cube_device(
                cube_d.reshape(h, w, m), psf if deblurred else 0.0,
                clip_max=cfg.max_reflectance,
            )  # fmt: skip
        cube, kkt_all = shard.to_host_copy(cube_d), shard.to_host_copy(kkt_d)
        clipped, hot_done, deblurred = True, True, False
    else:
        if not _all_finite(cube):  # never hand out NaN: the no-event answer,
            bad = ~np.isfinite(cube)  # flagged (kkt = inf)
            cube[bad] = _no_event_answer(rig, m)
            kkt_all[np.any(bad, axis=1)] = np.inf
        if gain is not None:
            cube = cube * gain
    if hot.any() and not hot_done:  # hot pixels carry no light information: fill
        # from their neighbours
        cube = _fill_from_neighbours(cube.reshape(h, w, m), hot, counts.reshape(h, w))
    if deblurred:
        cube = deblur_cube(cube.reshape(h, w, m), psf)
    if not clipped:  # (in place: the cube is this call's own array)
        np.clip(cube, 0.0, cfg.max_reflectance, out=cube)
    cube = cube.reshape(h, w, m)
    if not return_info:
        return cube
    info = ReconstructionInfo(
        events=counts.reshape(h, w),
        kkt=kkt_all.reshape(h, w),
        solved=(counts > 0).reshape(h, w),
        t_start_us=t_start_us,
        sweeps=sweeps,
        hot_pixels=hot,
        dropped_events=n_dropped,
        sweeps_left_out=left_out,
        events_left_out=n_all - len(events),
        first_sweep=first,
        stray_events=strays,
        sweep_speed=None if factors is None else np.asarray(factors, np.float64),
    )
    return cube, info


BACKENDS = ("auto", "jax", "fused", "cuda")


#: Whether `backend="auto"` picks the CUDA kernel on a CUDA GPU where it applies
#: (numba's CUDA target installed, the active-set solver, a float32 rig, one
#: device), for a call of at least `AUTO_CUDA_MIN_PIXELS` pixel·sweeps, and once it
#: passes its self-check (`_cuda_kernel.self_check`, once per process). The kernel
#: is kept in numba's on-disk cache (`_cuda_kernel.CACHE`), so a new process loads it
#: instead of compiling it; what stays is numba-cuda's own start in each process,
#: ~1.1 s on an H100's host (its import 0.53 s, its target's set-up 0.59 s, in a
#: profile). Measured on an H100 (experiments/PERFORMANCE_LOG.md, "One GPU"): a warm whole
#: 1280×720 sweep takes 0.51 s with the kernel and 0.68 s with JAX (0.68 s against
#: 1.00 s with the noise model), at the same accuracy against a float64 solve; whole
#: `evhsi reconstruct` processes with both caches filled: 96×144, 6.6 s against
#: 5.4 s (numba's start); 1280×720, 7.3–8.9 s against 6.2–8.0 s (six runs against
#: four on two machines: a wash); with the caches off (each process compiles),
#: 1280×720, 19.4–23.7 s against 23.8–24.7 s.
AUTO_CUDA = True
#: The smallest call (pixels × sweeps) for which `auto` takes the CUDA kernel:
#: small calls lose numba's start; from a 1280×720 sweep on, one call is a wash and
#: every further call or sweep in the process gains (~0.17 s per 1280×720 sweep),
#: as does a run that has to compile. 2^19 ≈ 0.52 M pixel·sweeps.
AUTO_CUDA_MIN_PIXELS = 2**19


def _use_cuda(backend, fused, spec, cfg, rig, mesh, work=None) -> bool:
    """Whether the chunks go to the CUDA kernel: asked for (`"cuda"`, a `ValueError`
    says why it cannot run), or `"auto"` on a CUDA GPU where it applies when
    `AUTO_CUDA` and the call's `work` (pixels × sweeps; None: large) is at least
    `AUTO_CUDA_MIN_PIXELS` (a failed self-check: a warning, and JAX)."""
    if fused or backend not in ("cuda", "auto"):
        return False
    small = work is not None and work < AUTO_CUDA_MIN_PIXELS
    if backend == "auto" and (
        not AUTO_CUDA or small or shard.device_platform(mesh) != "gpu"
    ):  # fmt: skip
        return False
    try:
        from . import _cuda_kernel
    except Exception as err:  # numba's CUDA target missing or broken
        if backend == "cuda":
            raise ValueError(f"the cuda backend cannot run: {err}") from err
        return False
    why = _cuda_kernel.why_not(spec, cfg, rig.fwhm_nm.dtype, mesh)
    if backend == "cuda" and why is not None:
        raise ValueError(f"the cuda backend cannot run this reconstruction: {why}")
    if why is None and backend == "auto":
        failed = _cuda_kernel.self_check(int(rig.channels))
        if failed is not None:
            warnings.warn(
                f"the CUDA kernel failed its self-check ({failed}); reconstructing "
                "with JAX (backend='jax' says so without this check)",
                RuntimeWarning, stacklevel=3,
            )  # fmt: skip
            return False
    return why is None


@jax.jit
def _any_failed(x, pixel):
    """Whether a real pixel (index ≥ 0) of a chunk has a non-finite answer."""
    return jnp.any((pixel >= 0) & ~jnp.all(jnp.isfinite(x), axis=1))


@functools.partial(jax.jit, donate_argnums=(0, 1))
def _place(cube, kkt_all, pixel, x, kkt):
    """The chunk's answers into the device's cube (padding rows, index −1, dropped)."""
    at = jnp.where(pixel >= 0, pixel, cube.shape[0])
    return (
        cube.at[at].set(x.astype(cube.dtype), mode="drop"),
        kkt_all.at[at].set(kkt.astype(kkt_all.dtype), mode="drop"),
    )


@functools.partial(jax.jit, static_argnums=(4,), donate_argnums=(0, 1))
def _finish_on_device(cube, kkt_all, no_event, gain, clip_max):
    """What `reconstruct` does to the host's cube after the solves, on the device's
    cube: non-finite answers replaced by the no-event answer `no_event` and flagged
    (KKT = inf), multiplied by the inverse white-reference gains `gain` `(M,)`
    (None: none), clipped to [0, `clip_max`] (None: not here; the host clips after
    its hot-pixel fill or deblurring). The same values as the host's NumPy passes."""
    bad = ~jnp.isfinite(cube)
    cube = jnp.where(bad, jnp.asarray(no_event, cube.dtype), cube)
    kkt_all = jnp.where(jnp.any(bad, axis=1), jnp.inf, kkt_all)
    if gain is not None:
        cube = cube * gain
    if clip_max is not None:
        cube = jnp.clip(cube, 0.0, jnp.asarray(clip_max, cube.dtype))
    return cube, kkt_all


#: Where the JAX backend sorts the events by pixel and cuts the padded batches:
#: `"auto"` on the device when it is an accelerator (:class:`._pixels.DeviceLists`;
#: the host's per-event passes cost several times a GPU's whole solve), on the host
#: (numba, :func:`._pixels.group_pixels`) on a CPU or a device mesh; `True` / `False`
#: force it (tests). The same batches either way; the cube is bit for bit the same
#: without carried references (tests/reconstruction/test_reconstruct.py).
DEVICE_GROUPING = "auto"


def _all_finite(a: np.ndarray) -> bool:
    """Whether every entry of `a` is finite, by its minimum and maximum (NaN and
    ±inf carry through them) instead of a mask: the mask of a 1280×720 cube took
    0.17 s in a 6.2 s reconstruction (two 66 MB arrays, each page first touched),
    the two reductions ~0.02 s."""
    return a.size == 0 or bool(np.isfinite(a.min()) and np.isfinite(a.max()))


def _solve_fused_all(
    rig, table, cfg, spec, sweeps, lists, lead, offsets, thr_on, thr_off, cube, kkt_all,
    threads, progress, noise=None, repair=False,
):  # fmt: skip
    """Every pixel with events through the fused CPU kernel (:mod:`._fused`), into
    `cube` and `kkt_all` (each block of answers as it is solved); a pixel whose
    float64 factorisation failed (a system singular to rounding: not seen in tests) is
    re-solved by :func:`_solve_robust`. `repair`: then :func:`repair_strays`.
    Returns the number of stray events removed."""
    counts, starts, t_rel, sgn = lists
    sel = np.flatnonzero(counts)
    if sel.size == 0:
        return
    w = offsets.size
    prob = FusedProblem(rig, table, cfg, spec, w, offsets, sweeps, noise)
    # The pixels in the kernel's order: its answers then need no moving back (three
    # copies, 0.34 s of a 360x640 realistic sweep's 7.3 s).
    order = prob.kernel_order(sel)
    if order is not None:
        sel = sel[order]
    fit = np.empty((sel.size, 3))
    _, _, steps = solve_fused(
        prob, sel, starts, counts, t_rel, sgn, lead, thr_on, thr_off,
        threads=threads, progress=progress, out=(cube, kkt_all), fit=fit,
    )  # fmt: skip
    strays = 0
    if repair and np.any(np.nan_to_num(fit[:, 0], nan=0.0) > cfg.stray_z):
        # The variants are solved without the robust reweighting: the one without
        # the stray has no outlier left, and the others' misfit is what tells them
        # apart (and the reweighting's passes made them 1.6× slower).
        plain = FusedProblem(
            rig, table, dataclasses.replace(cfg, robust_steps=0), spec, w, offsets,
            sweeps, noise,
        )  # fmt: skip
        solve_variants = functools.partial(
            _solve_variants, plain, lists, lead, thr_on, thr_off, threads=threads
        )
        pix, xs, kkts, strays = repair_strays(
            solve_variants, sel, fit, lists, cfg,
            float(_rig_geometry(rig, w)["period_us"]),
        )  # fmt: skip
        if strays:
            cube[pix], kkt_all[pix] = xs, kkts
    bad = np.flatnonzero(steps < 0)
    if bad.size:  # their events in padded slots, as group_pixels would give them
        pix = sel[bad]
        slot = np.arange(int(counts[pix].max()))
        mask = slot[None, :] < counts[pix][:, None]
        at = np.where(mask, starts[pix][:, None] + slot, 0)
        dtype = np.dtype(rig.fwhm_nm.dtype)
        px = _device_pixels(
            t_rel[at], np.where(mask, sgn[at], 0), mask, pix, pix % w, lead[pix],
            offsets, thr_on, thr_off, dtype,
        )  # fmt: skip
        noise_j = None if noise is None else jax.device_put(np.asarray(noise, dtype))
        cube[pix], kkt_all[pix] = _solve_robust_at(
            rig, table, cfg, spec, px, np.arange(bad.size), sweeps, noise_j
        )
    return strays


#: Flagged pixels' variants solved per call of the kernel (bounds the variants'
#: event lists: a pixel of k events has k variants of k − 1 events each).
STRAY_BLOCK = 4096
#: The first candidates: the events within this many of the worst row's.
STRAY_WINDOW = 4


def _sweep_span(t_rel, start, k, i, period_us):
    """For pixels whose events are `t_rel[start : start + k]` (µs from the
    recording's start, in time order): the first and last index (within the pixel)
    of the events in the same sweep as event `i`."""

    def sweep(j):  # (of the events looked at only, not of the whole recording)
        return np.floor(t_rel[start + j] / period_us)

    own = sweep(i)
    lo, hi = i.copy(), i.copy()
    while True:  # (a sweep holds a few dozen events: a few vectorised steps)
        more = (lo > 0) & (sweep(np.maximum(lo - 1, 0)) == own)
        if not more.any():
            break
        lo = lo - more
    while True:
        more = (hi < k - 1) & (sweep(np.minimum(hi + 1, k - 1)) == own)
        if not more.any():
            break
        hi = hi + more
    return lo, hi


def repair_strays(solve_variants, sel, fit, lists, cfg, period_us):
    """Find and remove stray events inside the lit interval (one or two per pixel).

    A background event inside a pixel's lit interval is not a threshold crossing of
    the light, yet its row and the next one's reference say it is. The solve can fit
    it by bending the spectrum (25° SAM on average on such pixels of a 20 Hz
    simulation of `tcs` on an ideal sensor, 17° with threshold noise 0.01 at 1 Hz),
    and the robust reweighting cannot see it afterwards (masking).

    A pixel whose worst event row is left more than `cfg.stray_z` standard
    deviations from its answer (the kernel's `out_fit`; in development runs on
    `tcs` no pixel without a background event was) is solved again without each
    of its events in turn — its neighbours' rows then link past the event left
    out, as the simulator's noise, which does not reset the pixel's reference,
    makes them — in three stages, each for the pixels the one before did not
    repair: the events within `STRAY_WINDOW` of the worst row's, the rest of its
    sweep, the other sweeps' (a stray event in one sweep bends the spectrum that
    all sweeps share, so the worst row can lie in another; stopping after the
    worst row's sweep left 4 sweeps of `tcs` at 1 Hz at 38.0 dB against 40.4 dB).
    A stage's variant with the smallest sum of squared residuals replaces the
    answer when its worst row is within `cfg.stray_z` and the sum fell by more
    than `cfg.stray_z`²; otherwise the pixel keeps its answer (a bad fit with
    another cause is not "repaired" by dropping a real event). A pixel left
    unrepaired whose best variant lowered the sum by more than `cfg.stray_z`² gets
    a second round on top of that variant (two strays in one recording: several
    sweeps at a higher rate; 4 sweeps of `tcs` at 1 Hz, 40.4 → 44.3 dB; at 3 Hz
    34.8 → 38.6 dB), with the same test against the first round's sum.

    `solve_variants(orig, drops)` solves, for each variant v, pixel `orig[v]`'s
    events without those `drops[v]` (`(n, d)`) names and returns `(x, kkt, fit)` per variant (fit as
    the kernel's, inf where a solve failed): :func:`_solve_variants` (fused) or
    :func:`_solve_variants_jax`, each without the robust reweighting (the variant
    without the stray has no outlier left, and the others' misfit is what tells
    them apart). `sel`, `fit`: the solved pixels (flat indices) and their fits;
    `lists`: the pixels' event lists (:func:`._pixels.pixel_lists`).

    **Returns:** `(pixels, x, kkt, removed)` — the repaired pixels, their new
    answers (None when there are none) and the number of events removed (one per
    pixel, two where a second round found a second stray)."""
    counts, starts, t_rel, _ = lists
    z = fit[:, 0]
    flag = np.flatnonzero(np.nan_to_num(z, nan=0.0) > cfg.stray_z)
    flag = flag[counts[sel[flag]] >= 2]
    out_pix, out_x, out_kkt = [], [], []
    removed = 0
    for b0 in range(0, flag.size, STRAY_BLOCK):
        f = flag[b0 : b0 + STRAY_BLOCK]
        pix = sel[f]
        k = counts[pix].astype(np.int64)
        worst = np.clip(fit[f, 1].astype(np.int64), 0, k - 1)
        none = np.full((pix.size, 0), -1, np.int64)
        ok, x, kkt, seen = _search_strays(
            solve_variants, lists, cfg, period_us, pix, k, worst, fit[f, 2], none
        )
        out_pix.append(pix[ok])
        out_x.append(x)
        out_kkt.append(kkt)
        removed += int(ok.sum())
        # A second stray (several sweeps at a higher rate): where one event's
        # removal lowered the misfit by a lot without making it clean, search for a
        # second on top of it.
        chi1, drops1, worst1 = seen
        two = np.flatnonzero(~ok & (chi1 < fit[f, 2] - cfg.stray_z**2) & (k >= 3))
        if two.size:
            ok2, x2, kkt2, _ = _search_strays(
                solve_variants, lists, cfg, period_us, pix[two], k[two], worst1[two],
                chi1[two], drops1[two],
            )  # fmt: skip
            out_pix.append(pix[two[ok2]])
            out_x.append(x2)
            out_kkt.append(kkt2)
            removed += 2 * int(ok2.sum())
    pix = np.concatenate(out_pix) if out_pix else np.zeros(0, np.int64)
    if pix.size == 0:
        return pix, None, None, 0
    x = np.concatenate([a for a in out_x if len(a)])
    return pix, x, np.concatenate([a for a in out_kkt if len(a)]), removed


def _search_strays(solve_variants, lists, cfg, period_us, pix, k, worst, base_chi,
                   base_drops):  # fmt: skip
    """One round of :func:`repair_strays` for the pixels `pix` (`k` events each,
    worst row at event `worst`, misfit `base_chi`), each with the events
    `base_drops` `(n, d)` left out already: their variants without one more event,
    in three stages. Returns `(ok, x, kkt, seen)` — which pixels were repaired, the
    repaired ones' answers, and for every pixel its best variant of all stages
    `(chi, drops (n, d + 1), worst event)` (chi inf where none was solved)."""
    _, starts, t_rel, _ = lists
    n = pix.size
    z2 = cfg.stray_z**2
    lo, hi = _sweep_span(t_rel, starts[pix], k, worst, period_us)
    near_lo = np.maximum(lo, worst - STRAY_WINDOW)
    near_hi = np.minimum(hi, worst + STRAY_WINDOW)
    ok = np.zeros(n, bool)
    rep, x_rep, kkt_rep = [], [], []  # each stage's repaired pixels and answers
    seen_chi = np.full(n, np.inf)
    seen_drops = np.full((n, base_drops.shape[1] + 1), -1, np.int64)
    seen_worst = worst.copy()
    # First the events near the worst row, then, for the pixels that found no
    # stray there, the rest of its sweep, then the other sweeps' events.
    todo = np.arange(n)
    for stage in range(3):
        if stage == 0:
            ranges = [(near_lo[todo], near_hi[todo])]
        elif stage == 1:
            ranges = [(lo[todo], near_lo[todo] - 1), (near_hi[todo] + 1, hi[todo])]
        else:
            ranges = [(np.zeros_like(todo), lo[todo] - 1), (hi[todo] + 1, k[todo] - 1)]
        sizes = [np.maximum(b - a + 1, 0) for a, b in ranges]
        owner = np.concatenate([np.repeat(todo, c) for c in sizes])
        drop = np.concatenate([np.repeat(a, c) + _ramp(c) for (a, _), c in zip(ranges, sizes)])
        keep = ~np.any(base_drops[owner] == drop[:, None], axis=1)  # (not twice)
        owner, drop = owner[keep], drop[keep]
        if owner.size == 0:
            break
        drops = np.concatenate([base_drops[owner], drop[:, None]], axis=1)
        vx, vkkt, vfit = solve_variants(pix[owner], drops)
        # Each pixel's best variant: the smallest sum of squared residuals.
        chi = vfit[:, 2]
        best_chi = np.full(n, np.inf)
        np.minimum.at(best_chi, owner, chi)
        best = np.full(n, -1, np.int64)
        is_best = chi == best_chi[owner]
        best[owner[is_best]] = np.flatnonzero(is_best)  # (ties: the last)
        better = (best >= 0) & (best_chi < seen_chi)
        seen_chi[better] = best_chi[better]
        seen_drops[better] = drops[best[better]]
        v_worst = np.clip(vfit[best[better], 1], 0, None).astype(np.int64)
        seen_worst[better] = _undropped(v_worst, drops[best[better]])
        good = (best >= 0) & (best_chi < base_chi - z2)
        good[good] = vfit[best[good], 0] <= cfg.stray_z
        rep.append(np.flatnonzero(good))
        x_rep.append(vx[best[good]])
        kkt_rep.append(vkkt[best[good]])
        ok |= good
        todo = todo[~good[todo]]
    if not rep:  # (no variant to solve)
        return ok, np.zeros((0, 0)), np.zeros(0), (seen_chi, seen_drops, seen_worst)
    order = np.argsort(np.concatenate(rep))  # the answers in the order of `pix`
    x, kkt = np.concatenate(x_rep)[order], np.concatenate(kkt_rep)[order]
    return ok, x, kkt, (seen_chi, seen_drops, seen_worst)


def _undropped(idx, drops):
    """Indices within the pixel's own events of the events `idx` of variants whose
    events `drops` `(n, d)` (−1: none) were left out."""
    out = np.asarray(idx, np.int64).copy()
    order = np.where(drops < 0, np.iinfo(np.int64).max, drops)
    for d in np.sort(order, axis=1).T:  # ascending: each skip moves the later ones
        out += out >= d
    return out


def _ramp(n):
    """0, 1, …, n[0] − 1, 0, 1, …, n[1] − 1, …"""
    return np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)


def _variant_lists(lists, orig, drop):
    """The event lists of variants: variant v is pixel `orig[v]`'s events without
    those `drop[v]` names (`(n,)` or `(n, d)`, −1: none). Returns `(vk, vstart,
    src)`: each variant's event count and start in the concatenated lists, and the
    source index (into the pixels' lists) of each of their events."""
    counts, starts, _, _ = lists
    drop = np.asarray(drop, np.int64).reshape(orig.size, -1)
    vk = counts[orig] - np.sum(drop >= 0, axis=1)
    vstart = np.cumsum(vk) - vk
    vown = np.repeat(np.arange(orig.size), vk)
    slot = np.arange(int(vk.sum())) - vstart[vown]
    return vk, vstart, starts[orig[vown]] + _undropped(slot, drop[vown])


def _solve_variants(prob, lists, lead, thr_on, thr_off, orig, drop, *, threads=None):
    """:func:`repair_strays`' variants through the fused kernel. Each variant is a
    virtual pixel in its pixel's column (the kernel looks the column offset up by
    index mod width), one virtual row per variant of that column. Returns `(x, kkt,
    fit)` per variant (fit inf where a factorisation failed)."""
    _, _, t_rel, sgn = lists
    w = prob.width
    nv = orig.size
    vk, vstart, src = _variant_lists(lists, orig, drop)
    col = orig % w
    order = np.argsort(col, kind="stable")
    rank = np.empty(nv, np.int64)
    rank[order] = np.arange(nv) - np.searchsorted(col[order], col[order])
    vpix = rank * w + col
    size = (int(rank.max()) + 1) * w
    v_starts, v_use = np.zeros(size, np.int64), np.zeros(size, np.int64)
    v_starts[vpix], v_use[vpix] = vstart, vk
    lead_v, on_v, off_v = np.zeros(size), np.ones(size), np.ones(size)
    lead_v[vpix], on_v[vpix], off_v[vpix] = lead[orig], thr_on[orig], thr_off[orig]
    fit = np.empty((nv, 3))
    x, kkt, steps = solve_fused(
        prob, vpix, v_starts, v_use, t_rel[src], sgn[src], lead_v, on_v, off_v,
        threads=threads, fit=fit,
    )  # fmt: skip
    fit[steps < 0] = np.inf
    return x, kkt, fit


def _solve_variants_jax(
    rig, table, cfg, spec, sub, chunk, sweeps, noise, lists, lead, offsets, thr_on,
    thr_off, dtype, orig, drop,
):  # fmt: skip
    """:func:`repair_strays`' variants through the JAX chunk kernel (`cfg` without
    the robust reweighting), in chunks of at most `chunk` rows padded as the main
    loop pads its own (`sub` × 2^j rows, 16 × 2^j slots: mostly shapes compiled
    already). Returns NumPy `(x, kkt, fit)` per variant (fit inf where x is not
    finite)."""
    _, _, t_rel, sgn = lists
    w = offsets.size
    vk, vstart, src = _variant_lists(lists, orig, drop)
    k = bucket_sizes(int(vk.max()))[-1]
    slot = np.arange(k)
    xs, kkts, fits = [], [], []
    for c0 in range(0, orig.size, chunk):
        o = orig[c0 : c0 + chunk]
        n_pad = sub * (1 << int(math.ceil(math.log2(math.ceil(o.size / sub)))))
        mask = np.zeros((n_pad, k), bool)
        mask[: o.size] = slot[None, :] < vk[c0 : c0 + o.size, None]
        at = np.zeros((n_pad, k), np.int64)
        at[: o.size] = vstart[c0 : c0 + o.size, None] + slot[None, :]
        at = np.where(mask, src[np.minimum(at, max(src.size - 1, 0))], 0)
        pix = np.zeros(n_pad, np.int64)
        pix[: o.size] = o
        px = _device_pixels(
            np.where(mask, t_rel[at], 0.0), np.where(mask, sgn[at], 0), mask, pix,
            pix % w, np.where(np.arange(n_pad) < o.size, lead[pix], 0.0), offsets,
            thr_on, thr_off, dtype,
        )  # fmt: skip
        x, kkt = _solve_chunk_stored(rig, table, cfg, spec, sub, px, sweeps, noise)
        fit = np.array(_chunk_fit(rig, table, cfg, px, sweeps, noise, x,
                                  float(noise[2]) > 0))  # fmt: skip
        x, kkt = np.asarray(x), np.asarray(kkt)
        fit[~np.all(np.isfinite(x), axis=1)] = np.inf
        xs.append(x[: o.size])
        kkts.append(kkt[: o.size])
        fits.append(fit[: o.size])
    return np.concatenate(xs), np.concatenate(kkts), np.concatenate(fits)


@eqx.filter_jit
def _chunk_fit(rig, table, cfg: ProblemConfig, px: PixelEvents, sweeps: int, noise, x,
               lowpass: bool):  # fmt: skip
    """Each pixel's fit to its event rows at its answer `x`, as the fused kernel's
    `out_fit` (`(n, 3)`: the largest |residual| in σ, its event's slot, the sum of
    squares capped at `robust_reject`²); with a photoreceptor (`lowpass`) its
    model's rows linearised at `x`."""
    with jax.default_matmul_precision(MATMUL_PRECISION):
        rows = _batch_rows(rig, table, cfg, px, sweeps, noise, x if lowpass else None)
        z = jnp.abs(_standard_residuals(rows, x))
    z = jnp.where(px.mask, jnp.nan_to_num(z, nan=jnp.inf), 0.0)
    total = jnp.sum(jnp.minimum(z * z, cfg.robust_reject**2), axis=1)
    return jnp.stack([jnp.max(z, axis=1), jnp.argmax(z, axis=1).astype(z.dtype), total],
                     axis=1)  # fmt: skip


#: Events per thread task of the numba screening (slices run on every usable core).
SCREEN_SLICE = 1 << 21


def screen_events(
    events, rig, t_start_us, noise, sweeps, hot_map=None, *, margin_us=None
):
    """Drop events no light change can have caused, and find hot pixels.

    The band touches column x only during its lit interval of each sweep (the band
    centre within 2 FWHM of the channel range, :func:`lit_interval_us`). An event
    outside that interval, widened by a margin for the photoreceptor's settling at
    the baseline light, timing jitter and calibration error (200 µs + 5 σ_t +
    $3 d_w/c$, at most 5 ms for the lag), is background activity or a hot pixel's:
    dropped. A pixel with on average ≥ 2 such events per sweep (and ≥ 2 in all) is
    hot — background activity of even 10 Hz gives ~0.1 per sweep — and so is every
    pixel of `hot_map`; hot
    pixels' events are all dropped and their spectra filled in from neighbours.

    **Returns:** `(events, hot, dropped)` — the kept events, the hot-pixel mask
    `(H, W)` and the number of events dropped.
    """
    keep, n_kept, hot, dropped = _screen_mask(
        events, rig, t_start_us, noise, sweeps, hot_map, margin_us
    )
    return (events if keep is None else _take_kept(events, keep, n_kept)), hot, dropped


def _screen_mask(events, rig, t_start_us, noise, sweeps, hot_map=None, margin_us=None):
    """:func:`screen_events` without taking the kept events: `(keep, n_kept, hot,
    dropped)`, `keep` a bool per event or None when every event is kept (the
    device's grouping drops the others where it sorts them: no copy here)."""
    h, w = events.height, events.width
    hot = np.zeros(h * w, bool) if hot_map is None else hot_map.reshape(-1).copy()
    if len(events) == 0:
        return None, 0, hot.reshape(h, w), 0
    geo = {k: np.asarray(v, np.float64) for k, v in _rig_geometry(rig, w).items()}
    period, t_arrive, t_leave = float(geo["period_us"]), geo["arrive"], geo["leave"]
    sig_t = 0.0 if noise is None else float(noise[1])
    d_base = 0.0 if noise is None else float(noise[2]) / float(rig.baseline_rel + 1e-3)
    margin = 200.0 + 5.0 * sig_t + min(3.0 * d_base, 5000.0)
    if margin_us is not None:
        margin = max(margin, float(margin_us))

    def flat_pixel(sel=slice(None)):  # flat index y·W + x of the events `sel`
        return events.y[sel].astype(np.int64) * w + events.x[sel]

    n = len(events)
    numba = use_numba()  # (the NumPy code is the reference)
    if numba:
        from ._group_jit import drop_hot, lit_mask

        inside = np.empty(n, bool)
        lo_col, hi_col = t_arrive - margin, t_leave + margin
        _in_screen_slices(n, lambda i0, i1: lit_mask(
            events.x[i0:i1], events.t_us[i0:i1], np.int64(t_start_us), period,
            lo_col, hi_col, inside[i0:i1],
        ))  # fmt: skip
    else:
        x = events.x.astype(np.int64)
        local = np.mod(events.t_us.astype(np.float64) - t_start_us, period)
        lo, hi = t_arrive[x] - margin, t_leave[x] + margin
        # The interval may wrap around the period (local times are taken modulo P).
        inside = (
            ((local >= lo) & (local <= hi))
            | ((local + period >= lo) & (local + period <= hi))
            | ((local - period >= lo) & (local - period <= hi))
        )
    out = np.flatnonzero(~inside)  # few: noise and hot pixels' events
    outside = np.bincount(flat_pixel(out), minlength=h * w)
    hot |= (outside >= 2) & (outside >= 2 * sweeps)
    if not hot.any():
        return (None if out.size == 0 else inside), n - out.size, hot.reshape(h, w), out.size
    if numba:
        keep = np.empty(n, bool)
        hot_ro = readonly(hot, bool)
        n_kept = int(sum(_in_screen_slices(n, lambda i0, i1: drop_hot(
            readonly(events.x[i0:i1], events.x.dtype),
            readonly(events.y[i0:i1], events.y.dtype), readonly(inside[i0:i1], bool),
            hot_ro, np.int64(w), keep[i0:i1],
        ))))  # fmt: skip
    else:
        keep = inside & ~hot[flat_pixel()]
        n_kept = int(keep.sum())
    return (None if n_kept == n else keep), n_kept, hot.reshape(h, w), n - n_kept


def _in_screen_slices(n: int, part) -> list:
    """`[part(i0, i1)]` over the slices of `SCREEN_SLICE` events covering [0, n), in
    order, on the usable cores when there are several slices (numba's kernels
    release the GIL)."""
    bounds = [(i0, min(i0 + SCREEN_SLICE, n)) for i0 in range(0, n, SCREEN_SLICE)]
    if len(bounds) < 2 or shard.usable_cores() < 2:
        return [part(*b) for b in bounds]
    with concurrent.futures.ThreadPoolExecutor(shard.usable_cores()) as pool:
        return list(pool.map(lambda b: part(*b), bounds))


def _take_kept(events, keep, n_kept):
    """`events.take(keep)`: with numba, slices compacted on the usable cores (each
    slice's kept events go to its offset), else NumPy's boolean indexing."""
    n = len(events)
    if not use_numba() or n <= SCREEN_SLICE or shard.usable_cores() == 1:
        return events.take(keep)
    from ._group_jit import compact_events

    counts = _in_screen_slices(n, lambda i0, i1: int(np.count_nonzero(keep[i0:i1])))
    offsets = np.cumsum([0] + counts[:-1])
    src = (events.x, events.y, events.p, events.t_us)
    out = tuple(np.empty(n_kept, a.dtype) for a in src)
    _in_screen_slices(n, lambda i0, i1: compact_events(
        readonly(keep[i0:i1], bool), *(readonly(a[i0:i1], a.dtype) for a in src),
        *out, np.int64(offsets[i0 // SCREEN_SLICE]),
    ))  # fmt: skip
    return dataclasses.replace(events, x=out[0], y=out[1], p=out[2], t_us=out[3])


def _fill_from_neighbours(cube, hot, counts):
    """Each hot pixel's spectrum: the median of its 8 neighbours that are neither hot
    nor without events (or of all solved pixels when none is): :func:`_hot_fill` of
    the host's cube `(H, W, M)`, a new cube."""
    h, w, m = cube.shape
    flat = cube.reshape(h * w, m)
    at, vals = _hot_fill(hot, counts, lambda idx: flat[idx], lambda sel: flat[sel])
    out = flat.copy()
    n = int(np.count_nonzero(hot))
    out[at[:n]] = vals[:n]
    return out.reshape(h, w, m)


def _fill_from_neighbours_device(cube, hot, counts):
    """:func:`_fill_from_neighbours` of a JAX cube `(H·W, M)` on its device: the
    hot pixels' 3×3 neighbourhoods are gathered there and brought over (a few
    hundred kB), their medians taken here by the host's code (the same values), and
    set there. `hot`, `counts`: `(H, W)` host arrays."""
    at, vals = _hot_fill(
        hot, counts, lambda idx: np.asarray(_gather_rows(cube, jax.device_put(idx))),
        lambda sel: np.asarray(cube)[sel],
    )  # fmt: skip
    return _set_rows(cube, *jax.device_put((at, vals)))


def _hot_fill(hot, counts, gather, rows_where):
    """The hot pixels' fill: `(at, values)`, the flat indices of the hot pixels
    (`hot`, `counts`: `(H, W)`) and for each the median of its 8 neighbours that
    are neither hot nor without events — or, where none is, of all such pixels (of
    every pixel when there are none) — padded to a power of two of rows with index
    H·W (few compiled shapes where they are gathered and set on a device).
    `gather(idx)`: the cube's rows at the flat indices `idx` `(n, 9)` as a NumPy
    `(n, 9, M)` array; `rows_where(mask)`: its rows where the flat `mask` is set."""
    h, w = hot.shape
    good = ~hot & (counts > 0)
    ys, xs = np.nonzero(hot)
    n_pad = 1 << int(math.ceil(math.log2(ys.size)))
    dy, dx = np.divmod(np.arange(9), 3)
    yy, xx = ys[:, None] + dy - 1, xs[:, None] + dx - 1
    inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
    yc, xc = np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)
    use = inside & good[yc, xc]
    flat = np.zeros((n_pad, 9), np.int32)
    flat[: ys.size] = yc * w + xc
    nb = gather(flat)
    vals = np.zeros((n_pad, nb.shape[2]), nb.dtype)
    whole = None
    for i in range(ys.size):
        if use[i].any():
            vals[i] = np.median(nb[i][use[i]], axis=0)
        else:  # no usable neighbour (rare): the median of all solved pixels
            if whole is None:
                whole = rows_where(good.reshape(-1) if good.any() else np.ones(h * w, bool))
            vals[i] = np.median(whole, axis=0)
    at = np.full(n_pad, h * w, np.int32)  # (padding: dropped)
    at[: ys.size] = ys * w + xs
    return at, vals


@jax.jit
def _gather_rows(cube, idx):
    return cube[idx]


@functools.partial(jax.jit, donate_argnums=(0,))
def _set_rows(cube, at, vals):
    return cube.at[at].set(vals, mode="drop")


def _speed_setting(sweep_speed, sweeps):
    """`reconstruct`'s `sweep_speed` checked: `"auto"`, None (`"off"`) or the
    factors as an array of `sweeps` (a `ValueError` says what is wrong)."""
    if isinstance(sweep_speed, str):
        if sweep_speed == "auto":
            return "auto"
        if sweep_speed == "off":
            return None
        raise ValueError(
            f"sweep_speed must be 'auto', 'off' or one factor per sweep, not "
            f"{sweep_speed!r}"
        )
    f = np.atleast_1d(np.asarray(sweep_speed, np.float64))
    if f.ndim != 1 or f.size != sweeps:
        raise ValueError(
            f"sweep_speed has {f.size} factor(s); the recording uses {sweeps} sweep(s)"
        )
    if not np.all(np.isfinite(f)) or np.any(np.abs(f - 1.0) > SPEED_BOUND):
        raise ValueError(f"sweep_speed factors must lie within 1 ± {SPEED_BOUND}")
    return f


def _candidate_lists(events, keep, counts, sweeps, t_start_us):
    """The host's event lists (:func:`pixel_lists`) of the pixels that may take part
    in the speed estimate (:func:`._sweep_speed.candidates`), kept events only: what
    the estimate needs when the lists themselves are made on the device."""
    w = events.width
    take = np.zeros(counts.size, bool)
    take[speed_candidates(counts, sweeps)] = True
    sel = take[events.y.astype(np.int64) * w + events.x.astype(np.int64)]
    if keep is not None:
        sel &= keep
    return pixel_lists(events.take(sel), t_start_us)


def _estimate_speeds(rig, cfg, spec, w, offsets, sweeps, noise, lists, lead, thr_on,
                     thr_off, period, threads):  # fmt: skip
    """:func:`._sweep_speed.estimate_speeds` with a setting the fused kernel runs
    (the active-set solver and the linear lookup, whatever the call's)."""
    if fused_supported(spec, cfg) is not None:
        spec = solver_spec("active-set")
        cfg = dataclasses.replace(cfg, lookup_order=1, nonneg=True)
    if noise is None:  # (an ideal sensor: rows weighted as for a small noise)
        noise = IDEAL_NOISE
    return estimate_speeds(
        rig, channel_table(rig), cfg, spec, w, offsets, sweeps, noise, lists, lead,
        thr_on, thr_off, period, threads=threads,
    )  # fmt: skip


def _reference_lead_us(reference_us, t_start_us, period, h, w) -> np.ndarray:
    """Per pixel, how long before `t_start_us` its reference was set, reduced modulo
    the period into [0, P) (only its place in the sweep matters: the pixel did not
    fire in between). Shifting the pixel's times by it and passing minus it as the
    phase puts its first reference at the reference time, the rest unchanged."""
    if reference_us is None:
        return np.zeros(h * w)
    ref = np.asarray(reference_us, np.float64)
    if ref.shape != (h, w):
        raise ValueError(f"reference_us has shape {ref.shape}, expected {(h, w)}")
    lead = np.nan_to_num(float(t_start_us) - ref.reshape(-1), nan=0.0)
    return np.mod(np.maximum(lead, 0.0), period)


def _check_map(a, h, w, name):
    a = np.asarray(a, np.float64)
    if a.shape != (h, w):
        raise ValueError(f"{name} has shape {a.shape}, expected {(h, w)}")
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise ValueError(f"{name} must be finite and > 0")
    return a.reshape(-1)


# --- the chunk kernel on a device mesh ----------------------------------------------
@functools.lru_cache(maxsize=64)
def _solver_fn(mesh, cfg, spec, sub, sweeps, with_noise):
    def local(rig, table, noise, px):
        noise = noise if with_noise else None
        return _solve_chunk(rig, table, cfg, spec, sub, px, sweeps, noise)

    mapped = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(P(), P(), P(), P(shard.PIXELS)),
        out_specs=(P(shard.PIXELS), P(shard.PIXELS)),
        check_vma=False,
    )
    return eqx.filter_jit(mapped)


def solve_chunk_sharded(
    mesh: Mesh,
    rig,
    table,
    cfg,
    spec,
    sub: int,
    px: PixelEvents,
    sweeps: int,
    noise=None,
):
    """The reconstruction's chunk kernel with its pixels split over `mesh`.

    Same arguments and results as :func:`_solve_chunk` (NumPy `(x, kkt)` out); the
    chunk's pixel count must be a multiple of `mesh.size * sub`.
    """
    n = np.shape(px.t_us)[0]
    if n % (shard.mesh_size(mesh) * sub):
        raise ValueError(
            f"chunk of {n} pixels does not split into {shard.mesh_size(mesh)}×{sub}"
        )
    rows = jax.tree.map(lambda a: shard.to_global(mesh, np.asarray(a)), px)
    fn = _solver_fn(mesh, cfg, spec, int(sub), int(sweeps), noise is not None)
    noise_arr = jnp.zeros(3, table.values.dtype) if noise is None else noise
    args = (
        shard.replicated(mesh, rig),
        shard.replicated(mesh, table),
        shard.replicated(mesh, noise_arr),
        rows,
    )
    x, kkt = call_exported(
        "reconstruct_chunk_sharded",
        fn,
        args,
        static=(cfg, spec, int(sub), int(sweeps), noise is not None),
        mesh=mesh,
    )
    return shard.to_host(x), shard.to_host(kkt)
