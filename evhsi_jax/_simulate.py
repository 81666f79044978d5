"""The exact event simulator: scene + rig → events, chunked over columns.

Work is split into chunks of whole columns (all rows of `chunk_columns` columns), so
memory is bounded by the chunk, not the sensor; every chunk has the same static shape, so
one compilation serves the whole sensor. Within a chunk only the time window in which the
band overlaps the channel range is scanned — outside it a pixel sees the constant light
alone and cannot fire. Pixels made of one spectrum share its intensity trace: a scene with
K distinct spectra costs K traces per column, not H.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import PRNGKeyArray
from tqdm.auto import tqdm

from . import _shard
from ._events import EventStream
from ._illumination import BandTable, band_table, lookup
from ._rig import Rig
from ._scenes import Scene
from ._sensor import exact_events_scan, initial_state
from ._spectra import band_integrate_matrix

__all__ = ["simulate", "SimulationInfo", "time_oversampling", "threshold_maps"]

MIN_SAMPLES_PER_FWHM = 12


@dataclasses.dataclass(frozen=True)
class SimulationInfo:
    """What the simulator drew and used, for truth files and tests."""

    threshold_on: np.ndarray  # (H, W) per-pixel ON thresholds, log units
    threshold_off: np.ndarray  # (H, W)
    samples_per_sweep: int  # time samples per sweep actually simulated
    window_samples: int  # samples scanned per chunk and sweep
    noise_events: int


def time_oversampling(rig: Rig) -> int:
    """Sub-samples per rig sample: the step must not exceed η (one event per step) and
    the band FWHM must span at least 12 steps (so linear log-interpolation is fine)."""
    dt = float(rig.period_us) / rig.samples_per_sweep
    speed = float(rig.beta_nm_per_rad * rig.omega_rad_per_us) * dt  # nm per sample
    by_refr = math.ceil(dt / float(rig.refractory_us) - 1e-9)
    by_band = math.ceil(MIN_SAMPLES_PER_FWHM * speed / float(rig.fwhm_nm) - 1e-9)
    return max(1, by_refr, by_band)


def threshold_maps(rig: Rig, height: int, width: int, *, key: PRNGKeyArray):
    """Per-pixel ON/OFF thresholds: $C = C_0 + δ$, $δ \\sim N(0, σ^2)$ per pixel.

    One deviation δ per pixel is shared by both polarities (the paper's
    "C ~ N(0.15, 0.01)" with symmetric triggering), so a pixel's ON and OFF thresholds
    differ by the rig's global `threshold_on - threshold_off` only. Clipped below at
    $0.1 C_0$ so a threshold is never ≤ 0.
    """
    delta = rig.threshold_sigma * jr.normal(key, (height, width))
    on = jnp.maximum(rig.threshold_on + delta, 0.1 * rig.threshold_on)
    off = jnp.maximum(rig.threshold_off + delta, 0.1 * rig.threshold_off)
    return np.asarray(on), np.asarray(off)


def _check_sweep_fits(rig: Rig, offsets: np.ndarray):
    """The band must be below the channels at t=0 and above them at t=P, per column."""
    lam0 = float(rig.sweep_start_nm)
    speed = float(rig.beta_nm_per_rad * rig.omega_rad_per_us)
    period = float(rig.period_us)
    fwhm = float(rig.fwhm_nm)
    start = lam0 + speed * offsets
    stop = lam0 + speed * (period + offsets)
    lo_need = rig.grid.start_nm - 2 * fwhm
    hi_need = rig.grid.stop_nm + 2 * fwhm
    if start.max() > lo_need + 1e-6:
        raise ValueError(
            f"the band starts at {start.max():.1f} nm for some column, above "
            f"{lo_need:.1f} nm (channel start - 2 FWHM): lower sweep_start_nm or the "
            "column offsets"
        )
    if stop.min() < hi_need - 1e-6:
        raise ValueError(
            f"the band reaches only {stop.min():.1f} nm by the end of the sweep for "
            f"some column, below {hi_need:.1f} nm (channel stop + 2 FWHM): increase "
            "beta_nm_per_rad or shorten the column offsets"
        )


def _windows(rig, table: BandTable, offsets, n_samples, dt, chunk_columns):
    """First sample index of each chunk's active window, and the common window length.

    The window covers band centres within 3 FWHM of the channel range (beyond, the band
    overlaps the channels by < 1e-10 of its peak), clipped to the table.
    """
    lam0 = float(rig.sweep_start_nm)
    speed = float(rig.beta_nm_per_rad * rig.omega_rad_per_us)
    margin = 3.0 * max(float(rig.fwhm_nm), 4.0)
    lo = max(table.lo_nm, rig.grid.start_nm - margin)
    hi = min(
        table.lo_nm + table.step_nm * (table.values.shape[0] - 1),
        rig.grid.stop_nm + margin,
    )
    t_lo = (lo - lam0) / speed - offsets
    t_hi = (hi - lam0) / speed - offsets
    j_lo = np.clip(np.floor(t_lo / dt).astype(int) - 1, 0, n_samples)
    j_hi = np.clip(np.ceil(t_hi / dt).astype(int) + 1, 0, n_samples)
    starts, lengths = [], []
    for c0 in range(0, offsets.size, chunk_columns):
        a, b = j_lo[c0 : c0 + chunk_columns].min(), j_hi[c0 : c0 + chunk_columns].max()
        starts.append(a)
        lengths.append(b - a + 1)
    length = min(n_samples + 1, 16 * math.ceil(max(lengths) / 16))
    starts = [min(s, n_samples + 1 - length) for s in starts]
    return starts, length


def _log_intensity(rig, table_values, lo_nm, t_local, offsets, spectra, labels):
    """log(I + ε) of one chunk of columns over one sweep window, shape `(t, c*h)`."""
    table = BandTable(table_values, lo_nm, 0.1)
    centres = rig.band_centre_nm(t_local[None, :], offsets[:, None])  # (c, t)
    a = lookup(table, centres)  # (c, t, f)
    if spectra.ndim == 2:  # palette: traces per spectrum, then gather by label
        traces = jnp.einsum("ctf,kf->ctk", a, spectra)
        inten = jnp.take_along_axis(traces, labels[:, None, :], axis=2)
    else:  # one spectrum per pixel: (c, h, f)
        inten = jnp.einsum("ctf,chf->cth", a, spectra)
    inten = inten + rig.baseline_rel
    log_i = jnp.log(jnp.maximum(inten, 0.0) + rig.log_eps)
    c, t, h = log_i.shape
    return jnp.transpose(log_i, (1, 0, 2)).reshape(t, c * h)


def _scan(rig, log_i, t_local, thr_on, thr_off, state):
    if state is None:
        state = initial_state(log_i[0])
    return exact_events_scan(
        log_i,
        t_local,
        thr_on,
        thr_off,
        rig.refractory_us,
        state,
        reset_mode=rig.reset_mode,
    )


_log_intensity_jit = eqx.filter_jit(_log_intensity)
_scan_jit = eqx.filter_jit(_scan)


@eqx.filter_jit
def _fused(rig, table_values, lo_nm, t_local, offsets, spectra, labels, *scan_args):
    log_i = _log_intensity(rig, table_values, lo_nm, t_local, offsets, spectra, labels)
    return _scan(rig, log_i, t_local, *scan_args)


def _chunk_kernel(
    rig, table_values, lo_nm, t_local, offsets, spectra, labels, thr_on, thr_off, state
):
    """Scan one chunk of columns over one sweep window. Shapes are static per run.

    The palette path runs as two compiled stages on purpose: compiled as one, XLA fuses
    the per-label gather (and log, transpose) into the scan's per-step reads, which
    made it ~2× slower on CPU (16 × 720 pixels × ~1000 steps); the per-pixel path is
    ~10 % faster fused.
    """
    if spectra.ndim == 2:
        log_i = _log_intensity_jit(
            rig, table_values, lo_nm, t_local, offsets, spectra, labels
        )
        out, state = _scan_jit(rig, log_i, t_local, thr_on, thr_off, state)
    else:
        out, state = _fused(
            rig,
            table_values,
            lo_nm,
            t_local,
            offsets,
            spectra,
            labels,
            thr_on,
            thr_off,
            state,
        )
    fired, tc, up = out
    return fired, tc, up, state


def simulate(
    scene: Scene | Sequence[Scene],
    rig: Rig,
    *,
    sweeps: int = 1,
    chunk_columns: int = 16,
    progress: bool = False,
    return_info: bool = False,
    mesh=None,
    key: PRNGKeyArray,
):
    """Simulate the event camera watching `scene` under the sweeping rainbow.

    **Arguments:**

    - `scene`: a static :class:`Scene`, or one scene per sweep (same size) for scenes
      that change between sweeps.
    - `rig`: the rig (thresholds are drawn per pixel with `rig.threshold_sigma`).
    - `sweeps`: number of sweeps; sweep `s` starts at $s P$ µs, marked by an external
      trigger (id 0, polarity 1) at `round(s * P)`.
    - `chunk_columns`: columns per chunk (memory ∝ chunk × window length).
    - `progress`: show a progress bar.
    - `return_info`: also return a :class:`SimulationInfo` (threshold maps, …).
    - `mesh`: a `jax.sharding.Mesh` (:func:`evhsi_jax.pixel_mesh`): run its
      `mesh.size` column chunks at once, one per device; the events equal the
      single-device run's. Default: one device.
    - `key`: PRNG key for thresholds and noise events.

    **Returns:** an :class:`EventStream` in time order (and the info if asked).
    """
    scenes = [scene] * sweeps if isinstance(scene, Scene) else list(scene)
    if sweeps < 1:
        raise ValueError(f"sweeps must be >= 1, got {sweeps}")
    if len(scenes) != sweeps:
        raise ValueError(f"got {len(scenes)} scenes for {sweeps} sweeps")
    h, w = scenes[0].height, scenes[0].width
    if any((s.height, s.width) != (h, w) for s in scenes):
        raise ValueError("all per-sweep scenes must have the same size")
    chunk_columns = max(1, min(int(chunk_columns), w))
    offsets = np.asarray(rig.column_offsets(w), np.float64)
    _check_sweep_fits(rig, offsets)
    k_thr, k_noise = jr.split(key)
    thr_on, thr_off = threshold_maps(rig, h, w, key=k_thr)

    os_ = time_oversampling(rig)
    n = rig.samples_per_sweep * os_
    period = float(rig.period_us)
    dt = period / n
    fine = band_table(rig)
    starts, length = _windows(rig, fine, offsets, n, dt, chunk_columns)

    # Work in the cheaper spectral basis: the scene's own samples or the fine sub-bins.
    bmat_cache = {}

    def basis(sc: Scene):
        k = id(sc.wavelengths_nm)
        if k not in bmat_cache:
            bmat_cache[k] = band_integrate_matrix(
                sc.wavelengths_nm, rig.grid.fine_edges_nm, name="scene"
            )
        bmat = bmat_cache[k]
        if bmat.shape[0] < bmat.shape[1]:
            tab = np.asarray(fine.values, np.float64) @ bmat.T
            return jnp.asarray(tab, fine.values.dtype), sc.palette
        return fine.values, sc.palette @ bmat

    # Pad the last chunk by repeating its final column; padded pixels are discarded.
    n_chunks = math.ceil(w / chunk_columns)
    col_index = np.minimum(np.arange(n_chunks * chunk_columns), w - 1).reshape(
        n_chunks, chunk_columns
    )
    dtype = fine.values.dtype
    out_cols = {k: [] for k in ("x", "y", "p", "t")}
    bar = tqdm(
        total=sweeps * n_chunks,
        disable=not progress,
        unit="chunk",
        desc=f"simulate {h}x{w}x{sweeps}",
    )
    groups = _shard.chunk_groups(n_chunks, mesh)  # one chunk each without a mesh
    group_states = [None] * len(groups)
    for s_idx, sc in enumerate(scenes):
        tab_vals, pal = basis(sc)
        use_palette = pal.shape[0] < h
        pal_j = jnp.asarray(pal, dtype)

        def chunk_inputs(ci, sc=sc, pal_j=pal_j, use_palette=use_palette):
            cols = col_index[ci]
            t_local = jnp.asarray((starts[ci] + np.arange(length)) * dt, dtype)
            lab = sc.labels[:, cols].T  # (c, h)
            spectra = pal_j if use_palette else pal_j[jnp.asarray(lab)]
            return (
                t_local,
                jnp.asarray(offsets[cols], dtype),
                spectra,
                jnp.asarray(lab),
                jnp.asarray(thr_on[:, cols].T.reshape(-1)),
                jnp.asarray(thr_off[:, cols].T.reshape(-1)),
            )

        for gi, group in enumerate(groups):
            state = group_states[gi]
            if state is not None:  # carry over: times relative to this sweep's start
                r, t_free, pend = state
                state = (r, t_free - period, pend)
            ins = [chunk_inputs(ci) for ci in group]
            if mesh is None:
                *out, group_states[gi] = _chunk_kernel(
                    rig, tab_vals, fine.lo_nm, *ins[0], state
                )
                outs = [out]
            else:
                t_loc, offs, spectra, lab, con, coff = (np.stack(a) for a in zip(*ins))
                spectra = pal_j if use_palette else spectra
                *out, group_states[gi] = _shard.scan_chunks_sharded(
                    mesh, rig, tab_vals, fine.lo_nm, spectra, t_loc, offs, lab, con,
                    coff, state,
                )  # fmt: skip
                outs = list(zip(*out))
            done = set()
            for ci, (fired, tc, up) in zip(group, outs):
                if ci in done:  # a repeat padding the last group
                    continue
                done.add(ci)
                cols = col_index[ci]
                fired = np.asarray(fired)
                step, pix = np.nonzero(fired)
                col_local, row = np.divmod(pix, h)
                keep = col_local < w - ci * chunk_columns  # drop padded columns
                step, pix = step[keep], pix[keep]
                col_local, row = col_local[keep], row[keep]
                out_cols["x"].append(cols[col_local].astype(np.uint16))
                out_cols["y"].append(row.astype(np.uint16))
                out_cols["p"].append(np.asarray(up)[step, pix].astype(np.uint8))
                # Index first, then widen: converting the whole (t, pixels) array to
                # float64 cost ~90 MB of copying per full-height chunk.
                t_abs = s_idx * period + np.asarray(tc)[step, pix].astype(np.float64)
                out_cols["t"].append(np.floor(t_abs).astype(np.int64))
                bar.update(1)
    bar.close()

    n_noise = 0
    if rig.noise_rate_hz > 0:
        noise = _noise_events(rig, h, w, sweeps * period, key=k_noise)
        n_noise = noise[0].size
        for k, v in zip(("x", "y", "p", "t"), noise):
            out_cols[k].append(v)
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out_cols.items()}
    order = np.argsort(cat["t"], kind="stable")
    trig = np.round(np.arange(sweeps) * period).astype(np.int64)
    events = EventStream(
        x=cat["x"][order],
        y=cat["y"][order],
        p=cat["p"][order],
        t_us=cat["t"][order],
        width=w,
        height=h,
        trigger_t_us=trig,
        trigger_p=np.ones(sweeps, np.uint8),
        trigger_id=np.zeros(sweeps, np.uint8),
    )
    if not return_info:
        return events
    info = SimulationInfo(thr_on, thr_off, n, length, n_noise)
    return events, info


def _noise_events(rig: Rig, h: int, w: int, duration_us: float, *, key):
    """Background activity: a Poisson process per pixel, random polarity.

    Noise events are added on top of the signal events and do not reset the pixel's
    reference (a simplification of real leak/shot-noise events).
    """
    rng = np.random.default_rng(np.asarray(jr.key_data(key)).ravel().tolist())
    count = rng.poisson(rig.noise_rate_hz * duration_us * 1e-6 * h * w)
    return (
        rng.integers(0, w, count).astype(np.uint16),
        rng.integers(0, h, count).astype(np.uint16),
        rng.integers(0, 2, count).astype(np.uint8),
        np.floor(rng.uniform(0, duration_us, count)).astype(np.int64),
    )
