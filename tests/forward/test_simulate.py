"""The exact event simulator, checked against the event model of paper Eq. 2.

The intensity a pixel sees is recomputed here in float64 NumPy from the band table,
the rig's sweep formula and the scene's spectra (averaged over the fine sub-bins by
dense quadrature), independently of the simulator's chunked, windowed JAX path.
"""

from __future__ import annotations

import logging
import math

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

from evhsi_jax import Rig, Scene, load_scene, simulate
from evhsi_jax._simulate._capture import time_oversampling
from evhsi_jax.forward import band_table, threshold_maps

H, W = 4, 6
KEY = jr.key(0)


# --- independent intensity model ------------------------------------------------------


def fine_palette(scene: Scene, rig: Rig, per_bin: int = 40) -> np.ndarray:
    """Mean of each palette spectrum over each fine sub-bin (midpoint rule), (K, F)."""
    e = rig.grid.fine_edges_nm
    frac = (np.arange(per_bin) + 0.5) / per_bin
    lam = (e[:-1, None] + np.diff(e)[:, None] * frac).ravel()
    vals = np.stack([np.interp(lam, scene.wavelengths_nm, p) for p in scene.palette])
    return vals.reshape(len(scene.palette), -1, per_bin).mean(-1)


class Model:
    """log(I(t) + ε) of any pixel at any absolute time, float64."""

    def __init__(self, scene: Scene, rig: Rig):
        table = band_table(rig)
        self.values = np.asarray(table.values, np.float64)
        self.lo, self.step = table.lo_nm, table.step_nm
        self.fine = fine_palette(scene, rig)
        self.labels = scene.labels
        self.offsets = np.asarray(rig.column_offsets(scene.width), np.float64)
        self.lam0 = float(rig.sweep_start_nm)
        self.speed = (
            float(rig.beta_nm_per_rad) * math.pi * float(rig.sweep_rate_hz) * 1e-6
        )
        self.period = 1e6 / float(rig.sweep_rate_hz)
        self.c = float(rig.baseline_rel)
        self.eps = float(rig.log_eps)

    def centre_nm(self, t_us, x):
        return self.lam0 + self.speed * (np.mod(t_us, self.period) + self.offsets[x])

    def log_i(self, t_us, x, y):
        pos = (self.centre_nm(np.asarray(t_us, np.float64), x) - self.lo) / self.step
        n = self.values.shape[0]
        inside = (pos >= 0) & (pos <= n - 1)
        i0 = np.clip(np.floor(pos), 0, n - 2).astype(int)
        frac = np.clip(pos - i0, 0, 1)[..., None]
        a = self.values[i0] * (1 - frac) + self.values[i0 + 1] * frac
        a = np.where(inside[..., None], a, 0.0)
        return np.log(a @ self.fine[self.labels[y, x]] + self.c + self.eps)


def pixel_events(ev, x, y):
    m = (ev.x == x) & (ev.y == y)
    return ev.t_us[m].astype(np.float64), ev.polarity_sign[m].astype(np.float64)


# --- scenes and simulations shared by several tests -----------------------------------


@pytest.fixture(scope="module")
def cc():
    return load_scene("colorchecker", (H, W))


@pytest.fixture(scope="module")
def sim_default(cc):
    """The paper rig (thresholds drawn with σ = 0.01), two sweeps."""
    rig = Rig()
    ev, info = simulate(cc, rig, sweeps=2, key=KEY, return_info=True)
    return rig, ev, info


@pytest.fixture(scope="module")
def sim_flat(cc):
    """Equal thresholds everywhere (σ = 0), one sweep."""
    rig = Rig(threshold_sigma=0.0)
    return rig, simulate(cc, rig, key=KEY)


def gray_ramp_scene(cc):
    """Flat gray spectra from reflectance 0.05 to 1, one per pixel (4 × 6)."""
    levels = np.linspace(0.05, 1.0, H * W)
    pal = np.repeat(levels[:, None], cc.wavelengths_nm.size, axis=1)
    return Scene(pal, cc.wavelengths_nm, np.arange(H * W).reshape(H, W)), levels


def hard_scene():
    """Rows: black, reflectance 1, a 5 nm laser line at 550 nm, gray 0.5."""
    wl = np.array([380.0, 547.4, 547.5, 552.5, 552.6, 780.0])
    pal = np.array(
        [
            np.zeros(6),
            np.ones(6),
            [0.0, 0.0, 1.0, 1.0, 0.0, 0.0],
            np.full(6, 0.5),
        ]
    )
    return Scene(pal, wl, np.repeat(np.arange(4)[:, None], W, axis=1))


# --- the event model ------------------------------------------------------------------


def check_release_identity(scene, rig, ev, info):
    """log(I(τ_k)+ε) − log(I(τ_{k−1}+η)+ε) = σ_k C (paper Eq. 2) for every pair of
    consecutive events of every pixel; the first event is measured from the constant
    light. Timestamps are whole µs (floored), so each side is bracketed over its
    microsecond. Returns the number of events checked."""
    model = Model(scene, rig)
    eta = float(rig.refractory_us)
    base = math.log(model.c + model.eps)
    u = np.array([0.0, 0.25, 0.5, 0.75, 1.0])[:, None]
    checked = 0
    for y in range(scene.height):
        for x in range(scene.width):
            t, s = pixel_events(ev, x, y)
            c = np.where(s > 0, info.threshold_on[y, x], info.threshold_off[y, x])
            a = model.log_i(t + u, x, y)  # (5, K)
            b = model.log_i(t[:-1] + eta + u, x, y)
            b = np.concatenate([np.full((5, 1), base), b], axis=1)
            lo = a.min(0) - b.max(0)
            hi = a.max(0) - b.min(0)
            target = s * c
            assert np.all(target >= lo - 2e-4), (y, x)
            assert np.all(target <= hi + 2e-4), (y, x)
            checked += t.size
    return checked


def test_release_identity_holds_for_every_event_pair(cc, sim_default):
    """Paper Eq. 2, both sweeps of the paper rig, across the sweep boundary too."""
    rig, ev, info = sim_default
    assert check_release_identity(cc, rig, ev, info) > 500


def test_state_carried_across_sweeps(cc):
    """A refractory time of 20 ms leaves pixels blind across the end of the sweep:
    they must be released (and their reference reset) one period later, in the next
    sweep, and never fire within η of their previous event."""
    rig = Rig(refractory_us=20000.0)
    ev, info = simulate(cc, rig, sweeps=3, key=KEY, return_info=True)
    assert check_release_identity(cc, rig, ev, info) > 60
    pix = ev.y.astype(np.int64) * W + ev.x
    order = np.lexsort((ev.t_us, pix))
    same = pix[order][1:] == pix[order][:-1]
    gaps = np.diff(ev.t_us[order])[same]
    assert gaps.min() >= 20000
    # Some pixel's blind time did span the end of a sweep.
    period = 1e6 / 30.0
    t0 = ev.t_us[order][:-1][same]
    assert np.any((t0 % period) + 20000 > period)
    # One trigger per sweep at round(s·P): 0, 33333.3 → 33333, 66666.7 → 66667.
    np.testing.assert_array_equal(ev.trigger_t_us, [0, 33333, 66667])


def test_summed_polarities_track_log_intensity(cc):
    """With a tiny refractory time, Σσ·C up to each event equals the change of
    log(I+ε) since the start within ±C, and the sweep ends where it began."""
    rig = Rig(refractory_us=1.0, threshold_sigma=0.0)
    ev = simulate(cc, rig, key=KEY)
    model = Model(cc, rig)
    c = 0.15
    base = math.log(model.c + model.eps)
    for y in range(H):
        for x in range(W):
            t, s = pixel_events(ev, x, y)
            assert t.size >= 6
            cum = np.cumsum(s) * c
            change = model.log_i(t + 0.5, x, y) - base
            np.testing.assert_array_less(np.abs(cum - change), c)
            assert abs(s.sum()) <= 1  # |Σσ·C| ≤ C at the end


@pytest.fixture(scope="module")
def sim_event(cc):
    """reset_mode="event" with a long refractory time (200 µs), so that it binds."""
    rig = Rig(reset_mode="event", threshold_sigma=0.0, refractory_us=200.0)
    return rig, simulate(cc, rig, key=KEY)


def test_event_mode_reference_steps_by_threshold(cc, sim_event):
    """reset_mode="event": the reference moves by exactly ±C per event, so at every
    event not delayed by the refractory period log(I+ε) − log(c+ε) = Σσ·C; a delayed
    one fires already past its threshold."""
    rig, ev = sim_event
    model = Model(cc, rig)
    base = math.log(model.c + model.eps)
    n_exact = n_late = 0
    for y in range(H):
        for x in range(W):
            t, s = pixel_events(ev, x, y)
            level = model.log_i(t[None] + np.array([[0.0], [1.0]]), x, y) - base
            miss = s * (level - np.cumsum(s) * 0.15)  # ≥ 0: at or past the threshold
            assert np.all(miss.max(0) >= -2e-3), (y, x)
            on_time = np.diff(t, prepend=-1e9) > float(rig.refractory_us) + 1
            assert np.all(miss.min(0)[on_time] <= 2e-3), (y, x)
            n_exact += on_time.sum()
            n_late += (miss.min(0)[~on_time] > 2e-3).sum()
    assert n_exact > 100 and n_late > 10


@pytest.mark.parametrize(
    "mode, refractory", [("release", 50.0), ("release", 200.0), ("event", 200.0)]
)
def test_no_two_events_closer_than_refractory(cc, sim_event, mode, refractory):
    if mode == "event":
        _, ev = sim_event
    else:
        ev = simulate(cc, Rig(refractory_us=refractory), key=KEY)
    pix = ev.y.astype(np.int64) * W + ev.x
    order = np.lexsort((ev.t_us, pix))
    same = pix[order][1:] == pix[order][:-1]
    gaps = np.diff(ev.t_us[order])[same]
    assert gaps.size > 100
    assert gaps.min() >= refractory
    if mode == "event":
        # Crossings during the blind time fire the moment it ends.
        assert np.sum(gaps == refractory) > 10


def test_event_count_scales_inverse_threshold(cc):
    """Flat gray pixels, tiny refractory time: the ON (OFF) count is the number of
    thresholds the log-level climbs (falls), floor(Δ/C), so halving C doubles it."""
    scene, levels = gray_ramp_scene(cc)
    counts = {}
    for c in (0.1, 0.2):
        rig = Rig(
            refractory_us=1.0, threshold_sigma=0.0, threshold_on=c, threshold_off=c
        )
        ev = simulate(scene, rig, key=KEY)
        model = Model(scene, rig)
        on = np.zeros((H, W))
        off = np.zeros((H, W))
        np.add.at(on, (ev.y, ev.x), ev.p == 1)
        np.add.at(off, (ev.y, ev.x), ev.p == 0)
        t = np.arange(0.0, model.period, 5.0)
        for y in range(H):
            for x in range(W):
                rise = model.log_i(t, x, y).max() - math.log(model.c + model.eps)
                # Release resets drift by ~slope·1 µs per event: allow one event less.
                assert rise / c - 2 < on[y, x] <= rise / c + 1e-6, (c, y, x)
                assert rise / c - 2 < off[y, x] <= rise / c + 1, (c, y, x)
        counts[c] = on + off
    bright = levels.reshape(H, W) >= 0.3
    ratio = counts[0.1][bright].sum() / counts[0.2][bright].sum()
    assert ratio == pytest.approx(2.0, abs=0.12)


def test_counts_monotone_in_gray_reflectance():
    """The gray chart's six neutral patches: brighter patch, more events, every column."""
    scene = load_scene("gray-chart", (12, W))
    rig = Rig(threshold_sigma=0.0)
    ev = simulate(scene, rig, key=KEY)
    counts = np.zeros((12, W))
    np.add.at(counts, (ev.y, ev.x), 1)
    mean_refl = scene.palette_on(rig.grid.edges_nm).mean(1)
    order = np.argsort(mean_refl)
    per_patch = np.stack([counts[scene.labels == k].reshape(2, W) for k in order])
    assert np.all(per_patch[:, 0] == per_patch[:, 1])  # rows of a stripe agree
    assert np.all(np.diff(per_patch[:, 0], axis=0) > 0)


# --- sweep geometry -------------------------------------------------------------------


@pytest.mark.parametrize("width", [6, 1280])
def test_every_channel_swept_once_per_sweep(width):
    """Per column, the band centre enters each channel range exactly once per period,
    and starts and ends the period ≥ 2 FWHM outside the channels."""
    rig = Rig()
    offsets = np.asarray(rig.column_offsets(width), np.float64)
    period = 1e6 / 30.0
    t = np.linspace(0.0, period, 20001)[:-1]
    edges = rig.grid.edges_nm
    cols = np.unique(np.linspace(0, width - 1, 6).astype(int))
    for x in cols:
        lam = np.asarray(rig.band_centre_nm(t, offsets[x]), np.float64)
        ch = np.searchsorted(edges, lam, side="right") - 1
        ch = np.where((lam < edges[0]) | (lam >= edges[-1]), -1, ch)
        for m in range(72):
            inside = (ch == m).astype(int)
            entries = np.sum(np.diff(np.concatenate([inside, inside[:1]])) == 1)
            assert entries == 1, (x, m)
        # Independently: λc = λ0 + βπf((t mod P) + τx) is monotone over the period.
        want = 360.0 + 185.0 * math.pi * 30e-6 * (t + offsets[x])
        np.testing.assert_allclose(lam, want, atol=2e-3)
        assert lam[0] <= 400.0 - 2 * 17.5 and lam[-1] >= 760.0 + 2 * 17.5


def test_columns_fire_in_sweep_order():
    """Identical white columns fire at times shifted by their offsets τx."""
    rig = Rig(threshold_sigma=0.0)
    ev = simulate(hard_scene(), rig, key=KEY)
    offsets = np.asarray(rig.column_offsets(W), np.float64)
    first = np.array([ev.t_us[(ev.y == 1) & (ev.x == x)][0] for x in range(W)])
    np.testing.assert_allclose(first - first[0], -(offsets - offsets[0]), atol=2.0)


# --- hard cases -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"threshold_on": 0.05, "threshold_off": 0.05},
        {"threshold_on": 0.5, "threshold_off": 0.5},
        {"baseline_rel": 0.0},
        {"baseline_rel": 1e-9},
    ],
    ids=["default", "thr0.05", "thr0.5", "c0", "c1e-9"],
)
def test_hard_cases(overrides):
    rig = Rig(threshold_sigma=0.0, **overrides)
    scene = hard_scene()
    ev = simulate(scene, rig, key=KEY)
    model = Model(scene, rig)
    c_on = float(rig.threshold_on)
    assert ev.is_time_ordered()
    assert ev.t_us.min() >= 0 and ev.t_us.max() < model.period
    n = np.zeros((4, W), int)
    np.add.at(n, (ev.y, ev.x), 1)
    # Black: constant intensity (c, or exactly 0), never an event.
    assert np.all(n[0] == 0)
    rise = math.log((1.0 + model.c + model.eps) / (model.c + model.eps))
    for x in range(W):
        for row in (1, 2, 3):
            t, s = pixel_events(ev, x, row)
            assert s[0] == 1 and s[-1] == -1  # up the band's rising flank, then down
            assert (s > 0).sum() <= rise / c_on + 1
        # Laser line: every event while the band centre is within 3 FWHM of it.
        t, _ = pixel_events(ev, x, 2)
        assert np.all(np.abs(model.centre_nm(t, x) - 550.0) < 3 * 17.5)
    assert np.all(n[1] >= n[3])  # white ≥ gray
    assert np.all(n[3] >= 2)


# --- bookkeeping: determinism, order, geometry, triggers, chunks, sweeps, dtypes ------


def test_deterministic_for_a_key(cc, sim_default):
    rig, ev, info = sim_default
    again, info2 = simulate(cc, rig, sweeps=2, key=KEY, return_info=True)
    for k in ("x", "y", "p", "t_us", "trigger_t_us"):
        np.testing.assert_array_equal(getattr(ev, k), getattr(again, k))
    np.testing.assert_array_equal(info.threshold_on, info2.threshold_on)
    other, info3 = simulate(cc, rig, sweeps=2, key=jr.key(1), return_info=True)
    assert not np.array_equal(info.threshold_on, info3.threshold_on)
    assert len(other) != len(ev) or not np.array_equal(other.t_us, ev.t_us)


def test_thresholds_drawn_per_pixel(sim_default):
    rig, _, info = sim_default
    on, off = threshold_maps(rig, 64, 64, key=jr.key(5))
    assert on.shape == (64, 64)
    np.testing.assert_allclose(on.mean(), 0.15, atol=0.003)
    np.testing.assert_allclose(on.std(), 0.01, rtol=0.15)
    np.testing.assert_allclose(on - off, 0.0, atol=1e-7)  # symmetric rig: shared δ
    assert info.threshold_on.shape == (H, W)


def test_time_order_geometry_and_triggers(sim_default):
    rig, ev, info = sim_default
    assert (ev.width, ev.height) == (W, H)
    assert ev.is_time_ordered()
    assert ev.x.max() < W and ev.y.max() < H
    assert set(np.unique(ev.p)) == {0, 1}
    period = 1e6 / 30.0
    np.testing.assert_array_equal(ev.trigger_t_us, [0, round(period)])
    np.testing.assert_array_equal(ev.trigger_p, [1, 1])
    np.testing.assert_array_equal(ev.trigger_id, [0, 0])
    # Both sweeps have events, each inside its own period.
    sweep = ev.t_us // period
    assert set(np.unique(sweep)) == {0, 1}
    assert info.samples_per_sweep == 1200 * time_oversampling(rig)


def test_only_lit_pixels_fire():
    """A black scene with two reflecting pixels: events there and nowhere else."""
    wl = np.array([380.0, 780.0])
    labels = np.zeros((H, W), int)
    labels[2, 5] = 1
    labels[0, 1] = 2
    scene = Scene(np.array([[0.0, 0.0], [0.9, 0.9], [0.3, 0.3]]), wl, labels)
    ev = simulate(scene, Rig(), chunk_columns=4, key=KEY)
    lit = set(zip(ev.y.tolist(), ev.x.tolist()))
    assert lit == {(2, 5), (0, 1)}


@pytest.mark.parametrize("chunk", [1, 4, 16])
def test_chunk_columns_do_not_change_events(cc, sim_flat, chunk):
    rig, ref = sim_flat
    ev = simulate(cc, rig, chunk_columns=chunk, key=KEY)
    for k in ("x", "y", "p", "t_us"):
        np.testing.assert_array_equal(getattr(ev, k), getattr(ref, k))


def test_multi_sweep_continuity(cc, sim_default):
    """The first of two sweeps equals a one-sweep run; the second repeats it up to
    the pixels' carried-over state (reference, refractory)."""
    rig, ev, _ = sim_default
    one = simulate(cc, rig, key=KEY)
    period = 1e6 / 30.0
    first = ev.t_us < period
    for k in ("x", "y", "p", "t_us"):
        np.testing.assert_array_equal(getattr(ev, k)[first], getattr(one, k))
    n1 = np.zeros((H, W), int)
    n2 = np.zeros((H, W), int)
    np.add.at(n1, (ev.y[first], ev.x[first]), 1)
    np.add.at(n2, (ev.y[~first], ev.x[~first]), 1)
    assert np.abs(n1 - n2).max() <= 2


def test_per_sweep_scenes_carry_state(cc):
    """A dark sweep leaves every pixel as it started, so a scene that appears in the
    second sweep fires as in a one-sweep run, one period later."""
    dark = Scene(np.zeros((1, 2)), np.array([380.0, 780.0]), np.zeros((H, W), int))
    rig = Rig()
    ev = simulate([dark, cc], rig, sweeps=2, key=KEY)
    one = simulate(cc, rig, key=KEY)
    period = 1e6 / 30.0
    assert len(ev) == len(one) > 100
    assert ev.t_us.min() >= period - 1
    for y in range(H):
        for x in range(W):
            t2, s2 = pixel_events(ev, x, y)
            t1, s1 = pixel_events(one, x, y)
            np.testing.assert_array_equal(s2, s1)
            np.testing.assert_allclose(t2 - t1, period, atol=1.0)


def test_palette_and_per_pixel_paths_agree():
    """The same gray chart as 6 shared spectra (one trace per spectrum) and as one
    spectrum per pixel gives the same events."""
    shared = load_scene("gray-chart", (12, W))
    per_pixel = Scene(
        shared.palette[shared.labels.ravel()],
        shared.wavelengths_nm,
        np.arange(12 * W).reshape(12, W),
    )
    rig = Rig(threshold_sigma=0.0)
    a = simulate(shared, rig, key=KEY)
    b = simulate(per_pixel, rig, key=KEY)
    assert len(a) > 100
    for k in ("x", "y", "p"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    np.testing.assert_allclose(a.t_us, b.t_us, atol=1)


def test_scene_basis_and_fine_basis_agree(cc, sim_flat):
    """ColorChecker on its own 5 nm samples (cheaper basis) and resampled onto a
    0.5 nm grid (same piecewise-linear spectra; fine-grid basis): same events."""
    rig, ref = sim_flat
    wl = np.arange(380.0, 780.01, 0.5)
    dense = Scene(
        np.stack([np.interp(wl, cc.wavelengths_nm, p) for p in cc.palette]),
        wl,
        cc.labels,
    )
    ev = simulate(dense, rig, key=KEY)
    assert len(ev) == len(ref) > 100
    for y in range(H):
        for x in range(W):
            t_a, s_a = pixel_events(ev, x, y)
            t_b, s_b = pixel_events(ref, x, y)
            np.testing.assert_array_equal(s_a, s_b)
            np.testing.assert_allclose(t_a, t_b, atol=1.0)


def test_float32_and_float64_agree(cc, sim_flat):
    rig32, ev32 = sim_flat
    with jax.enable_x64(True):
        rig64 = Rig(threshold_sigma=0.0)
        assert rig64.fwhm_nm.dtype == np.float64
        ev64 = simulate(cc, rig64, key=KEY)
    n32 = np.zeros((H, W), int)
    n64 = np.zeros((H, W), int)
    np.add.at(n32, (ev32.y, ev32.x), 1)
    np.add.at(n64, (ev64.y, ev64.x), 1)
    assert np.abs(n32 - n64).max() <= 1
    assert (n32 != n64).sum() <= 2
    for y in range(H):
        for x in range(W):
            if n32[y, x] == n64[y, x]:
                t32, s32 = pixel_events(ev32, x, y)
                t64, s64 = pixel_events(ev64, x, y)
                np.testing.assert_array_equal(s32, s64)
                np.testing.assert_allclose(t32, t64, atol=1.0)


def test_bad_arguments(cc):
    rig = Rig()
    with pytest.raises(ValueError, match="sweeps"):
        simulate(cc, rig, sweeps=0, key=KEY)
    with pytest.raises(ValueError, match="scenes"):
        simulate([cc, cc], rig, sweeps=3, key=KEY)
    with pytest.raises(ValueError, match="same size"):
        simulate([cc, load_scene("colorchecker", (H, W + 1))], rig, sweeps=2, key=KEY)
    with pytest.raises(ValueError, match="column offsets"):
        simulate(cc, Rig(column_offsets_us=[0.0] * (W + 1)), key=KEY)
    with pytest.raises(ValueError, match="sweep_start_nm"):
        simulate(cc, Rig(sweep_start_nm=420.0), key=KEY)
    with pytest.raises(ValueError, match="beta_nm_per_rad"):
        simulate(cc, Rig(beta_nm_per_rad=60.0), key=KEY)


def test_no_recompilation_for_new_values(cc, sim_default):
    """A second run with other parameter values (thresholds, constant light) and
    another key reuses the compiled kernels."""

    class Collect(logging.Handler):
        def __init__(self):
            super().__init__()
            self.messages = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    handler = Collect()
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles(True):
            rig = Rig(threshold_on=0.2, threshold_off=0.12, baseline_rel=0.05)
            ev = simulate(cc, rig, sweeps=2, key=jr.key(7))
    finally:
        logger.removeHandler(handler)
    assert len(ev) > 100
    assert not [m for m in handler.messages if m.startswith("Compiling")]


def test_accelerator_event_extraction_matches_the_host_path():
    # On a GPU the simulator gathers each chunk's crossings on the device; the events
    # (order, times, polarities) must be those of the host path.
    from evhsi_jax._simulate._capture import _fired_events

    rng = np.random.default_rng(0)
    fired = rng.random((50, 70)) < 0.05
    tc = rng.random((50, 70)).astype(np.float32)
    up = rng.random((50, 70)) < 0.5
    args = (jnp.asarray(fired), jnp.asarray(tc), jnp.asarray(up))
    for a, b in zip(_fired_events(*args, True), _fired_events(*args, False)):
        np.testing.assert_array_equal(a, b)
    empty = _fired_events(
        jnp.zeros((4, 5), bool), args[1][:4, :5], args[2][:4, :5], False
    )
    assert all(a.size == 0 for a in empty)


# --- the compiled (numba) state machine of the CPU path ------------------------------


@pytest.mark.parametrize("reset_mode", ["release", "event"])
@pytest.mark.parametrize("noisy", [False, True])
def test_compiled_scan_matches_the_xla_scan(reset_mode, noisy):
    """`_scan_jit.events_scan` crosses where `exact_events_scan` does: the same steps,
    pixels and polarities, times equal to float32 rounding, the same final state."""
    pytest.importorskip("numba")
    from evhsi_jax._base import readonly
    from evhsi_jax._model._sensor import exact_events_scan, initial_state
    from evhsi_jax._simulate._scan_jit import events_scan

    rng = np.random.default_rng(5)
    nt, p = 400, 37
    t = np.cumsum(rng.uniform(5.0, 20.0, nt)).astype(np.float32)
    walk = np.cumsum(rng.normal(0, 0.08, (nt, p)), axis=0)
    log_i = (walk + np.sin(t[:, None] / 300.0)).astype(np.float32)
    on = rng.uniform(0.15, 0.3, p).astype(np.float32)
    off = rng.uniform(0.15, 0.3, p).astype(np.float32)
    noise = (0.02 * rng.normal(size=(nt - 1, p))).astype(np.float32)
    eta = np.float32(30.0)
    (fired, tc, up), state = exact_events_scan(
        jnp.asarray(log_i), jnp.asarray(t), jnp.asarray(on), jnp.asarray(off),
        jnp.asarray(eta), initial_state(jnp.asarray(log_i[0])), reset_mode=reset_mode,
        reference_noise=jnp.asarray(noise) if noisy else None,
    )  # fmt: skip
    r, t_free, pend = (np.array(a) for a in initial_state(jnp.asarray(log_i[0])))
    # The inputs read-only, as the simulator passes them (one compiled kernel).
    ro = lambda a: readonly(a, np.float32)  # noqa: E731
    step, pix, t_ev, up_ev, n = events_scan(
        ro(log_i), ro(t), ro(on), ro(off), eta, r, t_free, pend,
        reset_mode == "release", ro(noise if noisy else np.zeros((1, 1))), noisy,
        nt * p,
    )  # fmt: skip
    s_ref, p_ref = np.nonzero(np.asarray(fired))
    assert n == s_ref.size > 100
    np.testing.assert_array_equal(step[:n], s_ref)
    np.testing.assert_array_equal(pix[:n], p_ref)
    np.testing.assert_array_equal(up_ev[:n], np.asarray(up)[s_ref, p_ref])
    np.testing.assert_allclose(t_ev[:n], np.asarray(tc)[s_ref, p_ref], rtol=1e-6)
    np.testing.assert_allclose(r, np.asarray(state[0]), atol=1e-5)
    np.testing.assert_array_equal(pend, np.asarray(state[2]))


def test_simulate_compiled_scan_equals_xla_path():
    """`simulate` on a CPU (numba scan) and with `EVHSI_NO_NUMBA` (XLA scan): the same
    events, timestamps within 1 µs (float32 rounding at a µs boundary), with the
    realistic sensor's per-crossing noise and photoreceptor low-pass on."""
    pytest.importorskip("numba")
    from evhsi_jax._base._numba import use_backend

    rig = Rig(sensor="realistic")
    scene = load_scene("colorchecker", (6, 10))
    out = {}
    for backend in ("numpy", "numba"):
        with use_backend(backend):
            out[backend] = simulate(scene, rig, sweeps=2, key=jr.key(4))
    a, b = out["numpy"], out["numba"]
    assert len(a) == len(b) > 1000
    ka = np.lexsort((a.t_us, a.p, a.x, a.y))
    kb = np.lexsort((b.t_us, b.p, b.x, b.y))
    for k in ("x", "y", "p"):
        np.testing.assert_array_equal(getattr(a, k)[ka], getattr(b, k)[kb])
    dt = np.abs(a.t_us[ka].astype(np.int64) - b.t_us[kb].astype(np.int64))
    assert dt.max() <= 1 and np.mean(dt > 0) < 1e-3
