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
import functools
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P
from jaxtyping import PRNGKeyArray
from tqdm.auto import tqdm

from .._base import (
    band_integrate_matrix,
    check_fits,
    shard,
    stable_argsort_int,
    use_numba,
)
from .._model import (
    TABLE_STEP_NM,
    BandTable,
    EventStream,
    Rig,
    Scene,
    band_table,
    exact_events_scan,
    initial_state,
    lookup,
    photoreceptor_lowpass,
)

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
    hot_pixels: np.ndarray | None = None  # (H, W) bool: the simulated hot pixels
    speed_factor: np.ndarray | None = None  # (sweeps,) each sweep's mirror-speed factor


def time_oversampling(rig: Rig) -> int:
    """Sub-samples per rig sample: the step must not exceed η (one event per step) and
    the band FWHM must span at least 12 steps (so linear log-interpolation is fine)."""
    dt = float(rig.period_us) / rig.samples_per_sweep
    speed = float(rig.band_speed_nm_per_us) * dt  # nm per sample
    by_refr = math.ceil(dt / float(rig.refractory_us) - 1e-9)
    by_band = math.ceil(MIN_SAMPLES_PER_FWHM * speed / float(rig.fwhm_nm) - 1e-9)
    return max(1, by_refr, by_band)


def threshold_maps(rig: Rig, height: int, width: int, *, key: PRNGKeyArray):
    """Per-pixel ON/OFF thresholds: $C = C_0 + δ$, $δ \\sim N(0, σ^2)$ per pixel.

    The ON and OFF deviations have correlation ρ = `on_off_correlation`:
    $δ_{off} = ρ δ_{on} + \\sqrt{1-ρ^2}\\,σ z$. With the default ρ = 1 one deviation is
    shared by both polarities (the paper's "C ~ N(0.15, 0.01)" with symmetric
    triggering); real pixels differ per polarity (the `realistic` preset uses
    ρ = 0.5). Clipped below at $0.1 C_0$ so a threshold is never ≤ 0.
    """
    # (Python floats: a NumPy float64 times a JAX array would be computed by NumPy)
    sigma = float(rig.threshold_sigma)
    rho = float(rig.effects.on_off_correlation)
    delta = sigma * jr.normal(key, (height, width))
    delta_off = delta
    if rho < 1.0:
        own = sigma * jr.normal(jr.fold_in(key, 1), (height, width))
        delta_off = rho * delta + math.sqrt(1.0 - rho * rho) * own
    on = jnp.maximum(rig.threshold_on + delta, 0.1 * rig.threshold_on)
    off = jnp.maximum(rig.threshold_off + delta_off, 0.1 * rig.threshold_off)
    return np.asarray(on), np.asarray(off)


def _check_sweep_fits(rig: Rig, offsets: np.ndarray):
    """The band must be below the channels at t=0 and above them at t=P, per column."""
    lam0 = float(rig.sweep_start_nm)
    speed = float(rig.band_speed_nm_per_us)
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


#: Photoreceptor time constants at the constant light that a sweep's window runs on
#: after the band has left (:func:`_windows`): e^-5 of the last step is left, well
#: below a threshold.
SETTLE_TIME_CONSTANTS = 5.0


def _windows(rig, table: BandTable, offsets, n_samples, dt, chunk_columns):
    """First sample index of each chunk's active window, and the common window length.

    The window covers band centres within 3 FWHM of the channel range (beyond, the band
    overlaps the channels by < 1e-10 of its peak), clipped to the table; with a
    photoreceptor, also its settling after the band has left the channel range:
    `SETTLE_TIME_CONSTANTS` time constants at the constant light c (its cut-off
    there is c times the white one's), within the sweep (the 3 FWHM already cover a
    10 kHz photoreceptor's: its windows are as before). A slow photoreceptor (3 kHz:
    1.8 ms at the paper rig's c) was cut off mid-decay before: the next window starts
    settled, and the OFF events the decay still owed fired at once at its first
    sample, a burst no sensor gives.
    """
    lam0 = float(rig.sweep_start_nm)
    speed = float(rig.band_speed_nm_per_us)
    margin = 3.0 * max(float(rig.fwhm_nm), 4.0)
    lo = max(table.lo_nm, rig.grid.start_nm - margin)
    hi = min(
        table.lo_nm + table.step_nm * (table.values.shape[0] - 1),
        rig.grid.stop_nm + margin,
    )
    t_lo = (lo - lam0) / speed - offsets
    t_hi = (hi - lam0) / speed - offsets
    hz = float(rig.effects.photoreceptor_hz)
    if hz > 0:  # the decay after the band: until settled, or the sweep's end
        tau_dark = 1e6 / (2.0 * math.pi * hz * float(rig.baseline_rel))
        band_end = (rig.grid.stop_nm - lam0) / speed - offsets
        t_hi = np.maximum(t_hi, band_end + SETTLE_TIME_CONSTANTS * tau_dark)
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


def _log_intensity(
    rig, table_values, lo_nm, t_local, offsets, spectra, labels, lowpass_hz=None
):
    """log(I + ε) of one chunk of columns over one sweep window, shape `(t, c*h)`;
    through the photoreceptor low-pass when `lowpass_hz` (its cut-off at white) is
    given."""
    table = BandTable(table_values, lo_nm, TABLE_STEP_NM)
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
    log_i = jnp.transpose(log_i, (1, 0, 2)).reshape(t, c * h)
    if lowpass_hz is not None:
        log_i = photoreceptor_lowpass(
            log_i, t_local[1] - t_local[0], lowpass_hz, rig.log_eps
        )
    return log_i


def _trigger_scan(rig, log_i, t_local, thr_on, thr_off, state, ref_noise=None):
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
        reference_noise=ref_noise,
    )


_log_intensity_jit = eqx.filter_jit(_log_intensity)
_trigger_scan_jit = eqx.filter_jit(_trigger_scan)


@eqx.filter_jit
def _intensity_and_trigger(
    rig, table_values, lo_nm, t_local, offsets, spectra, labels, lowpass_hz, *scan_args
):
    log_i = _log_intensity(
        rig, table_values, lo_nm, t_local, offsets, spectra, labels, lowpass_hz
    )
    return _trigger_scan(rig, log_i, t_local, *scan_args)


def _chunk_kernel(
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
    lowpass_hz=None,
    ref_noise=None,
):
    """Scan one chunk of columns over one sweep window. Shapes are static per run.

    The palette path runs as two compiled stages on purpose: compiled as one, XLA fuses
    the per-label gather (and log, transpose) into the scan's per-step reads, which
    made it ~2× slower on CPU (16 × 720 pixels × ~1000 steps); the per-pixel path is
    ~10 % faster fused.
    """
    if spectra.ndim == 2:
        log_i = _log_intensity_jit(
            rig, table_values, lo_nm, t_local, offsets, spectra, labels, lowpass_hz
        )
        out, state = _trigger_scan_jit(
            rig, log_i, t_local, thr_on, thr_off, state, ref_noise
        )
    else:
        out, state = _intensity_and_trigger(
            rig,
            table_values,
            lo_nm,
            t_local,
            offsets,
            spectra,
            labels,
            lowpass_hz,
            thr_on,
            thr_off,
            state,
            ref_noise,
        )
    fired, tc, up = out
    return fired, tc, up, state


#: Columns per compiled chunk by device kind: on a CPU 16 columns keep one chunk's
#: scan state in cache (experiments/bench_simulate.py); a GPU needs ~10^5 pixels per
#: step of the scan to be busy (256 columns x 720 rows, ~1 GB per chunk).
CHUNK_COLUMNS = {"cpu": 16, "accelerator": 256}


def simulate(
    scene: Scene | Sequence[Scene],
    rig: Rig,
    *,
    sweeps: int = 1,
    chunk_columns: int | None = None,
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
    - `chunk_columns`: columns per chunk (memory ∝ chunk × window length). Default
      by device kind: 16 on a CPU, 256 on a GPU (`CHUNK_COLUMNS`). With per-crossing
      threshold noise the noise is drawn per chunk, so captures with different
      chunks differ in their noise draws (each is a valid draw).
    - `progress`: show a progress bar.
    - `return_info`: also return a :class:`SimulationInfo` (threshold maps, …).
    - `mesh`: a `jax.sharding.Mesh` (:func:`evhsi_jax.sharding.pixel_mesh`): run its
      `mesh.size` column chunks at once, one per device; the events equal the
      single-device run's. Default: one device.
    - `key`: PRNG key for thresholds and noise events.

    **Returns:** an :class:`EventStream` in time order (and the info if asked).
    """
    if sweeps < 1:
        raise ValueError(f"sweeps must be >= 1, got {sweeps}")
    scenes = None if isinstance(scene, Scene) else list(scene)
    if scenes is not None and len(scenes) != sweeps:
        raise ValueError(f"got {len(scenes)} scenes for {sweeps} sweeps")
    first = scene if scenes is None else scenes[0]
    # At least ~8 events of 13 bytes per pixel and sweep are kept in memory (a real
    # scene makes several times more): refuse what cannot fit before starting.
    check_fits(
        8 * 13 * float(sweeps) * first.height * first.width,
        f"simulating {sweeps} sweep(s) of {first.height}x{first.width} pixels",
    )
    scenes = [scene] * sweeps if scenes is None else scenes
    h, w = scenes[0].height, scenes[0].width
    if any((s.height, s.width) != (h, w) for s in scenes):
        raise ValueError("all per-sweep scenes must have the same size")
    on_host = shard.device_platform(mesh) == "cpu"
    if chunk_columns is None:
        chunk_columns = CHUNK_COLUMNS["cpu" if on_host else "accelerator"]
    chunk_columns = max(1, min(int(chunk_columns), w))
    offsets = np.asarray(rig.column_offsets(w), np.float64)
    _check_sweep_fits(rig, offsets)
    k_thr, k_noise = jr.split(key)
    thr_on, thr_off = threshold_maps(rig, h, w, key=k_thr)
    fx = rig.effects.floats()
    # Keys of the sensor effects, derived so that the ideal sensor's draws (thresholds,
    # background noise) are the same as without them.
    k_ref, k_time, k_hot, k_sweep = (jr.fold_in(key, 1000 + i) for i in range(4))
    if (fx.threshold_noise > 0 or fx.photoreceptor_hz > 0) and mesh is not None:
        raise ValueError(
            "threshold_noise and photoreceptor_hz are not simulated on a device mesh "
            "yet: simulate on one device"
        )
    if fx.psf_sigma_px > 0:
        scenes = [sc.blurred(fx.psf_sigma_px) for sc in scenes]
    speed_factor = np.ones(sweeps)
    if fx.sweep_rate_jitter > 0:
        speed_factor = 1.0 + fx.sweep_rate_jitter * np.asarray(
            jr.normal(k_sweep, (sweeps,)), np.float64
        )

    oversample = time_oversampling(rig)
    n = rig.samples_per_sweep * oversample
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
    groups = shard.chunk_groups(n_chunks, mesh)  # one chunk each without a mesh
    # On a CPU the state machine runs as a numba kernel (the same crossings, times to
    # float32 rounding; `_scan_jit`); `EVHSI_NO_NUMBA=1` keeps the XLA scan.
    compiled_scan = mesh is None and on_host and use_numba()
    group_states = [None] * len(groups)
    lowpass_hz = (
        jnp.asarray(fx.photoreceptor_hz, dtype) if fx.photoreceptor_hz > 0 else None
    )
    for s_idx, sc in enumerate(scenes):
        # Mirror-speed jitter: the whole sweep λc(t) runs faster or slower by a factor
        # (β·ω scales together), which is a change of β for this sweep.
        srig = rig
        if speed_factor[s_idx] != 1.0:
            srig = rig.with_leaves(
                beta_nm_per_rad=rig.beta_nm_per_rad * speed_factor[s_idx]
            )
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
                ref_noise = None
                if fx.threshold_noise > 0:
                    k = jr.fold_in(jr.fold_in(k_ref, s_idx), group[0])
                    shape = (length - 1, chunk_columns * h)
                    ref_noise = fx.threshold_noise * jr.normal(k, shape, dtype)
                if compiled_scan:
                    *out, group_states[gi] = _chunk_host_scan(
                        srig, tab_vals, fine.lo_nm, *ins[0], state, lowpass_hz,
                        ref_noise,
                    )  # fmt: skip
                else:
                    *out, group_states[gi] = _chunk_kernel(
                        srig, tab_vals, fine.lo_nm, *ins[0], state, lowpass_hz,
                        ref_noise,
                    )  # fmt: skip
                outs = [out]
            else:
                t_loc, offs, spectra, lab, con, coff = (np.stack(a) for a in zip(*ins))
                spectra = pal_j if use_palette else spectra
                *out, group_states[gi] = scan_chunks_sharded(
                    mesh, srig, tab_vals, fine.lo_nm, spectra, t_loc, offs, lab, con,
                    coff, state,
                )  # fmt: skip
                outs = list(zip(*out))
            done = set()
            for ci, res in zip(group, outs):
                if ci in done:  # a repeat padding the last group
                    continue
                done.add(ci)
                cols = col_index[ci]
                if compiled_scan:  # the crossings themselves
                    step, pix, t_ev, up_ev = res
                else:
                    step, pix, t_ev, up_ev = _fired_events(*res, on_host)
                col_local, row = np.divmod(pix, h)
                keep = col_local < w - ci * chunk_columns  # drop padded columns
                col_local, row = col_local[keep], row[keep]
                out_cols["x"].append(cols[col_local].astype(np.uint16))
                out_cols["y"].append(row.astype(np.uint16))
                out_cols["p"].append(up_ev[keep].astype(np.uint8))
                # Index first, then widen: converting the whole (t, pixels) array to
                # float64 cost ~90 MB of copying per full-height chunk.
                t_abs = s_idx * period + t_ev[keep].astype(np.float64)
                out_cols["t"].append(np.floor(t_abs).astype(np.int64))
                bar.update(1)
    bar.close()

    if fx.timestamp_jitter_us > 0 or fx.latency_us > 0:
        out_cols["t"] = _jittered(out_cols["t"], fx, key=k_time)
    n_noise = 0
    if rig.noise_rate_hz > 0:
        noise = _noise_events(rig, h, w, sweeps * period, key=k_noise)
        n_noise = noise[0].size
        for k, v in zip(("x", "y", "p", "t"), noise):
            out_cols[k].append(v)
    hot = np.zeros((h, w), bool)
    if fx.hot_pixel_fraction > 0:
        hot, extra = _hot_pixel_events(fx, h, w, sweeps * period, key=k_hot)
        for k, v in zip(("x", "y", "p", "t"), extra):
            out_cols[k].append(v)
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out_cols.items()}
    order = stable_argsort_int(cat["t"])  # O(n): a counting sort over the µs
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
    info = SimulationInfo(thr_on, thr_off, n, length, n_noise, hot, speed_factor)
    return events, info


def _chunk_host_scan(
    rig, table_values, lo_nm, t_local, offsets, spectra, labels, thr_on, thr_off,
    state, lowpass_hz=None, ref_noise=None,
):  # fmt: skip
    """:func:`_chunk_kernel` with the state machine in numba (`_scan_jit`): the log
    intensity from JAX, then the scan on the host. Returns `(step, pixel, time,
    is_on, state)` — the crossings, not dense arrays."""
    from .._base import readonly
    from ._scan_jit import events_scan

    log_i = readonly(
        np.asarray(
            _log_intensity_jit(
                rig, table_values, lo_nm, t_local, offsets, spectra, labels, lowpass_hz
            )
        ),
        np.float32,
    )
    t = readonly(np.asarray(t_local), np.float32)
    if state is None:  # the XLA path's starting state, as host arrays
        state = tuple(np.asarray(a) for a in initial_state(jnp.asarray(log_i[0])))
    noise = np.zeros((1, 1)) if ref_noise is None else np.asarray(ref_noise)
    noise = readonly(noise, np.float32)
    args = (
        log_i, t, readonly(np.asarray(thr_on), np.float32),
        readonly(np.asarray(thr_off), np.float32),
        np.float32(rig.refractory_us),
    )  # fmt: skip
    nt, p = log_i.shape
    span = float(t[-1] - t[0]) if nt > 1 else 0.0
    cap = p * min(nt - 1, int(span / max(float(rig.refractory_us), 1e-3)) + 2)
    while True:  # the kernel advances the state in place: hand it a copy
        st = tuple(np.array(a) for a in state)
        step, pix, tc, up, n = events_scan(
            *args, *st, rig.reset_mode == "release", noise, ref_noise is not None,
            max(cap, 1),
        )  # fmt: skip
        if n <= cap:
            return step[:n], pix[:n], tc[:n], up[:n], st
        cap = n


def _fired_events(fired, tc, up, on_host: bool):
    """`(step, pixel, time, polarity)` of a chunk's crossings, in `np.nonzero(fired)`
    order. On a CPU the dense `(t, pixels)` arrays are read directly; on an
    accelerator the crossings are gathered there and only they come back (the dense
    arrays of a 256-column chunk are ~1 GB: copying them to the host and scanning them
    took 7.4 s of a 1280x720 sweep on an H100, the device work 0.4 s)."""
    if on_host:
        fired, tc, up = np.asarray(fired), np.asarray(tc), np.asarray(up)
        step, pix = np.nonzero(fired)
        return step, pix, tc[step, pix], up[step, pix]
    n = int(jnp.count_nonzero(fired))
    size = 1 << max(10, (n - 1).bit_length())  # few compiled sizes
    out = _gather_fired(fired, tc, up, size)
    return tuple(np.asarray(a)[:n] for a in out)


@functools.partial(jax.jit, static_argnums=3)
def _gather_fired(fired, tc, up, size):
    step, pix = jnp.nonzero(fired, size=size, fill_value=0)
    return step, pix, tc[step, pix], up[step, pix]


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


def _rng(key) -> np.random.Generator:
    return np.random.default_rng(np.asarray(jr.key_data(key)).ravel().tolist())


def _jittered(times: list[np.ndarray], fx, *, key) -> list[np.ndarray]:
    """Add the constant latency and Gaussian timestamp jitter to integer µs times (the
    jittered crossing time is floored again, as the sensor's counter would)."""
    rng = _rng(key)
    out = []
    for t in times:
        d = fx.latency_us + fx.timestamp_jitter_us * rng.standard_normal(t.size)
        out.append(np.maximum(np.floor(t + 0.5 + d), 0).astype(np.int64))
    return out


def _hot_pixel_events(fx, h: int, w: int, duration_us: float, *, key):
    """Hot pixels: a fraction of the pixels fires all the time, independent of the
    light — a Poisson process at `hot_pixel_rate_hz` with alternating polarity (a
    leaky pixel's reference keeps walking one way and back). Returns the hot-pixel mask
    and the events `(x, y, p, t)`."""
    rng = _rng(key)
    n_hot = max(1, int(round(fx.hot_pixel_fraction * h * w)))
    flat = rng.choice(h * w, size=min(n_hot, h * w), replace=False)
    hot = np.zeros(h * w, bool)
    hot[flat] = True
    counts = rng.poisson(fx.hot_pixel_rate_hz * duration_us * 1e-6, flat.size)
    pix = np.repeat(flat, counts)
    t = np.floor(rng.uniform(0, duration_us, pix.size)).astype(np.int64)
    order = np.lexsort((t, pix))
    pix, t = pix[order], t[order]
    rank = np.arange(pix.size) - np.repeat(np.cumsum(counts) - counts, counts)
    p = (rank % 2).astype(np.uint8)
    y, x = np.divmod(pix, w)
    return hot.reshape(h, w), (x.astype(np.uint16), y.astype(np.uint16), p, t)


# --- the chunk kernel on a device mesh ----------------------------------------------
@functools.lru_cache(maxsize=64)
def _log_intensity_fn(mesh, palette: bool, lo_nm: float):
    def local(rig, tab, spectra, t_local, offsets, labels):
        spec = spectra if palette else spectra[0]
        log_i = _log_intensity(rig, tab, lo_nm, t_local[0], offsets[0], spec, labels[0])
        return log_i[None]

    rows = P(shard.PIXELS)
    mapped = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(P(), P(), P() if palette else rows, rows, rows, rows),
        out_specs=rows,
        check_vma=False,
    )
    return eqx.filter_jit(mapped)


@functools.lru_cache(maxsize=64)
def _scan_fn(mesh, fresh: bool):
    def local(rig, log_i, t_local, thr_on, thr_off, state):
        state = None if fresh else jax.tree.map(lambda a: a[0], state)
        out, state = _trigger_scan(
            rig, log_i[0], t_local[0], thr_on[0], thr_off[0], state
        )
        return jax.tree.map(lambda a: a[None], (*out, state))

    rows = P(shard.PIXELS)
    mapped = jax.shard_map(
        local,
        mesh=mesh,
        in_specs=(P(),) + (rows,) * 5,
        out_specs=rows,
        check_vma=False,
    )
    return eqx.filter_jit(mapped)


def scan_chunks_sharded(
    mesh: Mesh,
    rig,
    table_values,
    lo_nm: float,
    spectra,
    t_local,
    offsets,
    labels,
    thr_on,
    thr_off,
    state,
):
    """The simulator's chunk kernel on one group of `mesh.size` column chunks at once.

    Every argument after `spectra` has a leading axis of one entry per chunk
    (`spectra` too when it holds per-pixel spectra, `(D, c, h, f)`; a palette `(K, f)`
    is shared); `state` is `None` on the first sweep, else the stacked state the
    previous call returned. Two compiled stages (intensity, then the scan), as in the
    single-device palette path. Returns `(fired, time_us, is_on, state)`, stacked
    `(D, …)`: NumPy, the state as device arrays.
    """
    palette = np.ndim(spectra) == 2
    fresh = state is None
    g = functools.partial(shard.to_global, mesh)
    rig_r = shard.replicated(mesh, rig)
    log_i = _log_intensity_fn(mesh, palette, float(lo_nm))(
        rig_r,
        shard.replicated(mesh, table_values),
        shard.to_global(mesh, spectra, sharded=False) if palette else g(spectra),
        g(t_local),
        g(offsets),
        g(labels),
    )
    if fresh:  # a placeholder with the right leading axis; not read
        state = (g(np.zeros((shard.mesh_size(mesh), 1), np.float32)),) * 3
    fired, tc, up, new_state = _scan_fn(mesh, fresh)(
        rig_r, log_i, g(t_local), g(thr_on), g(thr_off), state
    )
    return (
        shard.to_host(fired),
        shard.to_host(tc),
        shard.to_host(up),
        new_state,
    )
