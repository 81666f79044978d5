"""Events → cube: group pixels, assemble each pixel's QP, solve, write back.

Work is proportional to each pixel's own event count (buckets of padded lengths 16, 32,
…), pixels without events cost no solve, and each bucket chunk is processed with
`lax.map` over sub-batches so the per-pixel matrices stay in cache and memory stays
bounded by the chunk.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .._events import EventStream
from .._illumination import band_table
from .._rig import Rig
from . import _solvers
from ._pixels import group_pixels
from ._problem import ProblemConfig, pixel_system

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


def _no_event_answer(rig: Rig, m: int) -> float:
    """Reflectance for a pixel without events: half the largest flat reflectance that
    stays below the ON threshold (a white-normalised peak of ρ gives ρ)."""
    c1 = float(rig.baseline_rel + rig.log_eps)
    return 0.5 * c1 * math.expm1(float(rig.threshold_on))


@eqx.filter_jit
def _solve_chunk(
    rig,
    table,
    cfg: ProblemConfig,
    spec: SolverSpec,
    sub: int,
    t_us,
    polarity,
    mask,
    offsets,
    thr_on,
    thr_off,
    phase,
    sweeps: int,
):
    """Assemble and solve a chunk of pixels; returns x (n, M) and KKT residuals.
    `phase` is a scalar or one value per pixel."""

    def system(t, p, mk, off, con, coff, ph):
        return pixel_system(rig, table, cfg, t, p, mk, off, con, coff, ph, sweeps)[:2]

    def one_batch(args):
        q_mat, q_vec = jax.vmap(system)(*args)
        if spec.name == "active-set":
            x, kkt, _ = _solvers.active_set_batch(
                q_mat, q_vec, tol=spec.tol, max_iters=spec.iters
            )
            return x, kkt
        if spec.name == "svd":
            gram = jax.vmap(lambda *a: _augmented_gram(rig, table, cfg, *a, sweeps))(
                *args
            )
            x = jax.vmap(_solvers.svd_nullvector)(gram)
        else:
            x = jax.vmap(lambda a, b: spec.solve(a, b, None))(q_mat, q_vec)
        return x, jax.vmap(_solvers.kkt_residual)(q_mat, q_vec, x)

    n = t_us.shape[0]
    phase = jnp.broadcast_to(jnp.asarray(phase, t_us.dtype), (n,))
    xs = (t_us, polarity, mask, offsets, thr_on, thr_off, phase)
    xs = jax.tree.map(lambda a: a.reshape((n // sub, sub) + a.shape[1:]), xs)
    x, kkt = jax.lax.map(one_batch, xs)
    return x.reshape(n, -1), kkt.reshape(n)


@eqx.filter_jit
def _solve_robust(
    rig,
    table,
    cfg: ProblemConfig,
    iters: int,
    t_us,
    polarity,
    mask,
    offsets,
    thr_on,
    thr_off,
    phase,
    sweeps: int,
):
    """The exact active-set solution pixel by pixel (`lax.map`), with Cholesky
    factorisations retried under a rounding-level shift where they fail
    (:func:`._solvers.cho_factor`). For the rare pixels whose batched solve came out
    non-finite: float32 systems that are indefinite by rounding (few events, weak
    priors). Same arguments as :func:`_solve_chunk`, minus the solver and sub-batch."""

    def one(args):
        t, p, mk, off, con, coff, ph = args
        q_mat, q_vec = pixel_system(
            rig, table, cfg, t, p, mk, off, con, coff, ph, sweeps
        )[:2]
        x = _solvers.active_set(q_mat, q_vec, iters=iters, robust=True)
        return x, _solvers.kkt_residual(q_mat, q_vec, x)

    n = t_us.shape[0]
    phase = jnp.broadcast_to(jnp.asarray(phase, t_us.dtype), (n,))
    return jax.lax.map(one, (t_us, polarity, mask, offsets, thr_on, thr_off, phase))


def _augmented_gram(rig, table, cfg, t, p, mk, off, con, coff, phase, sweeps):
    """$\\hat N^T \\hat N$ of the event rows alone (the paper's SVD system)."""
    bare = dataclasses.replace(cfg, alpha_int=0.0, alpha_spec=0.0, ridge=0.0)
    q_mat, q_vec, _ = pixel_system(
        rig, table, bare, t, p, mk, off, con, coff, phase, sweeps, return_gram=True
    )
    return q_mat


def reconstruct(
    events: EventStream,
    rig: Rig,
    *,
    solver: str | SolverSpec = "auto",
    config: ProblemConfig | None = None,
    threshold_on_map: np.ndarray | None = None,
    threshold_off_map: np.ndarray | None = None,
    t_start_us: int | None = None,
    reference_us: np.ndarray | None = None,
    chunk_pixels: int = 2048,
    sub_batch: int = 128,
    progress: bool = False,
    return_info: bool = False,
    mesh=None,
):
    """Reconstruct a reflectance cube from an event recording of a static scene.

    **Arguments:**

    - `events`: the recording (one or more sweeps of a static scene).
    - `rig`: the calibration (thresholds, β, τx, c, FWHM, D, E…).
    - `solver`: a name from `SOLVERS`, `"auto"`, or a :class:`SolverSpec`.
    - `config`: the per-pixel problem's weights (:class:`ProblemConfig`).
    - `threshold_on_map`, `threshold_off_map`: optional per-pixel thresholds `(H, W)`
      (log units) from a calibration; default the rig's global values.
    - `t_start_us`: time at which the recording's first sweep starts (sweep phase 0);
      default the first trigger, else 0.
    - `reference_us`: optional `(H, W)` times (µs, same clock as the events; NaN for
      none) at which each pixel's reference level was last set before `t_start_us` —
      the release $τ + η$ after its last earlier event. The pixel's first event then
      refers to the intensity at that time (under the spectrum being solved for)
      instead of the baseline c' at `t_start_us`: what a recording cut out of a longer
      one needs (:func:`evhsi_jax.reconstruct_sweeps`). Default: all at `t_start_us`.
    - `chunk_pixels`: pixels per compiled chunk (memory ∝ chunk × events per pixel).
    - `sub_batch`: pixels per `lax.map` step inside a chunk.
    - `progress`: show a progress bar.
    - `return_info`: also return a :class:`ReconstructionInfo`.
    - `mesh`: a `jax.sharding.Mesh` with a `"pixels"` axis
      (:func:`evhsi_jax.pixel_mesh`): each chunk's pixels are split over its devices,
      `chunk_pixels` per device, each with the same per-pixel kernel. A one-device
      mesh gives the plain run's cube bit for bit; on several CPU devices XLA compiles
      the kernel differently and the cube differs by float32 rounding (3e-5 on
      reflectance ~0.5 in tests/test_shard.py; solved pixels and event counts equal).
      Several CPU devices solve one pixel per sub-batch (see
      `evhsi_jax._shard.sub_batch_for`).

    **Returns:** the cube `(H, W, M)` float32 (and the info if asked). Never NaN: a
    pixel whose batched solve is non-finite (float32 rounding on a nearly singular
    system) is re-solved alone by the exact active-set method with shifted-retry
    factorisations; one still non-finite after that (or from `svd`/`unconstrained`)
    gets the no-event answer and KKT = inf.
    """
    spec = solver_spec(solver)
    cfg = config or ProblemConfig()
    h, w = events.height, events.width
    m = rig.channels
    offsets_all = np.asarray(rig.column_offsets(w), np.float64)
    if t_start_us is None:
        t_start_us = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    if len(events) and int(events.t_us[0]) < t_start_us:
        raise ValueError(
            f"events start at {int(events.t_us[0])} µs, before the sweep start "
            f"{t_start_us} µs"
        )
    period = float(rig.period_us)
    duration = float(events.t_us[-1] - t_start_us) if len(events) else 0.0
    sweeps = max(1, math.ceil((duration + 1.0) / period))
    sub = max(1, min(sub_batch, chunk_pixels))
    solve, n_dev = _solve_chunk, 1
    if mesh is not None:
        from .._shard import solve_chunk_sharded, sub_batch_for

        solve, n_dev = functools.partial(solve_chunk_sharded, mesh), mesh.devices.size
        sub = sub_batch_for(mesh, sub)
    chunk = sub * math.ceil(chunk_pixels / sub)
    batches, counts, _ = group_pixels(
        events, t_start_us=t_start_us, chunk_pixels=chunk * n_dev, min_chunk=sub * n_dev
    )
    lead = _reference_lead_us(reference_us, t_start_us, period, h, w)
    dtype = rig.fwhm_nm.dtype  # float32 or float64: the rig decides
    table = band_table(rig).channels(rig.grid.sub)
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

    cube = np.full((h * w, m), _no_event_answer(rig, m), np.float32)
    kkt_all = np.full(h * w, np.nan, np.float32)
    bar = tqdm(
        total=int(np.count_nonzero(counts)),
        disable=not progress,
        unit="px",
        desc=f"reconstruct ({spec.name})",
    )
    for b in batches:
        valid = b.pixel >= 0
        pix = np.where(valid, b.pixel, 0)
        # Carried references: shift each pixel's clock to start at its reference.
        d = np.where(valid, lead[pix], 0.0)
        args = (
            jnp.asarray(np.where(b.mask, b.t_us + d[:, None], 0.0), dtype),
            jnp.asarray(b.polarity, jnp.int32),
            jnp.asarray(b.mask),
            jnp.asarray(offsets_all[b.column], dtype),
            jnp.asarray(thr_on[pix], dtype),
            jnp.asarray(thr_off[pix], dtype),
            jnp.asarray(-d, dtype),
        )
        x, kkt = solve(rig, table, cfg, spec, sub, *args, sweeps)
        x, kkt = np.asarray(x), np.asarray(kkt)
        failed = valid & ~np.all(np.isfinite(x), axis=1)
        if failed.any() and spec.name not in ("svd", "unconstrained"):
            # Rare: re-solve the chunk's failed pixels exactly, one by one.
            x, kkt = x.copy(), kkt.copy()  # device buffers are read-only
            idx = np.flatnonzero(failed)
            n_pad = 1 << int(math.ceil(math.log2(idx.size)))  # few compiled sizes
            sel = np.concatenate([idx, np.full(n_pad - idx.size, idx[0])])
            xr, kr = _solve_robust(
                rig, table, cfg, max(spec.iters, 48), *(a[sel] for a in args), sweeps
            )
            x[idx], kkt[idx] = np.asarray(xr)[: idx.size], np.asarray(kr)[: idx.size]
        cube[b.pixel[valid]] = x[valid]
        kkt_all[b.pixel[valid]] = kkt[valid]
        bar.update(int(valid.sum()))
    bar.close()
    bad = ~np.isfinite(cube)
    if bad.any():  # never hand out NaN: the no-event answer, flagged (kkt = inf)
        cube[bad] = _no_event_answer(rig, m)
        kkt_all[np.any(bad, axis=1)] = np.inf
    if rig.channel_gain is not None:  # white-reference response correction
        cube = cube / np.asarray(rig.channel_gain, np.float32)
    cube = cube.reshape(h, w, m)
    if not return_info:
        return cube
    info = ReconstructionInfo(
        events=counts.reshape(h, w),
        kkt=kkt_all.reshape(h, w),
        solved=(counts > 0).reshape(h, w),
        t_start_us=t_start_us,
        sweeps=sweeps,
    )
    return cube, info


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
