"""Event triggering: the exact pixel state machine and its soft relaxation."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from evhsi_jax import Rig
from evhsi_jax.forward import (
    band_table,
    column_time_table,
    exact_events_scan,
    soft_event_counts,
    sweep_times_us,
)

# --- an independent reference: the pixel model of paper Eq. 2 in plain Python --------


def reference_events(level, t, c_on, c_off, eta, mode="release"):
    """Events of one pixel whose log-level is the piecewise-linear interpolant of
    `level` at times `t`: (time, +1/-1) pairs.

    The pixel starts sensitive with reference `level[0]`. While sensitive it fires at
    the first instant the level reaches reference + c_on (ON) or reference - c_off
    (OFF), then is blind for `eta`. In "release" mode its reference becomes the level
    at the end of the blind time; in "event" mode the reference steps by ±C at the event.
    """

    def at(x):
        return float(np.interp(x, t, level))

    events = []
    ref = float(level[0])
    t_from = float(t[0])
    while True:
        hit = None
        j0 = max(int(np.searchsorted(t, t_from, side="right")) - 1, 0)
        for j in range(j0, len(t) - 1):
            a = max(t_from, t[j])
            la, lb = at(a), level[j + 1]
            for sign, target in ((1, ref + c_on), (-1, ref - c_off)):
                if sign * (la - target) >= 0:  # already beyond (event mode only)
                    hit = (a, sign, target)
                elif sign * (lb - target) >= 0:
                    frac = (target - la) / (lb - la)
                    hit = (a + frac * (t[j + 1] - a), sign, target)
                if hit:
                    break
            if hit:
                break
        if hit is None:
            return events
        tc, sign, target = hit
        events.append((tc, sign))
        t_from = tc + eta
        if t_from > t[-1]:
            return events
        ref = at(t_from) if mode == "release" else target


def traces(seed, n_pix, n_t=400, dt=10.0):
    """Smooth random log-level traces (sums of Gaussian bumps and dips), (t, p)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_t) * dt
    out = np.zeros((n_t, n_pix))
    for p in range(n_pix):
        for _ in range(4):
            c, w = rng.uniform(0, t[-1]), rng.uniform(100, 600)
            out[:, p] += rng.uniform(-1.5, 2.5) * np.exp(-0.5 * ((t - c) / w) ** 2)
    return t, out


def events_of(fired, tc, up, p):
    f = np.asarray(fired)[:, p]
    return list(
        zip(np.asarray(tc, np.float64)[f, p], np.where(np.asarray(up)[f, p], 1, -1))
    )


@functools.partial(jax.jit, static_argnames="reset_mode")
def jit_scan(log_i, t, c_on, c_off, eta, *, reset_mode="release"):
    return exact_events_scan(log_i, t, c_on, c_off, eta, reset_mode=reset_mode)


@pytest.mark.parametrize("mode", ["release", "event"])
@pytest.mark.parametrize("eta", [10.0, 35.0, 200.0])
def test_exact_scan_matches_reference(mode, eta):
    with jax.enable_x64(True):
        t, level = traces(0, 6)
        c_on = np.array([0.15, 0.1, 0.2, 0.15, 0.12, 0.3])
        c_off = np.array([0.15, 0.12, 0.1, 0.2, 0.12, 0.25])
        (fired, tc, up), _ = jit_scan(
            jnp.asarray(level),
            jnp.asarray(t),
            jnp.asarray(c_on),
            jnp.asarray(c_off),
            jnp.asarray(eta),
            reset_mode=mode,
        )
    total = 0
    for p in range(6):
        want = reference_events(level[:, p], t, c_on[p], c_off[p], eta, mode)
        got = events_of(fired, tc, up, p)
        assert [s for _, s in got] == [s for _, s in want], p
        np.testing.assert_allclose([x for x, _ in got], [x for x, _ in want], atol=1e-6)
        total += len(want)
    assert total > 30  # the traces do exercise the model


def test_exact_scan_float32_agrees_with_float64():
    t, level = traces(1, 5)
    args = (level, t, np.full(5, 0.15), np.full(5, 0.13), 30.0)
    (f32, t32, u32), _ = jit_scan(*(jnp.asarray(a, jnp.float32) for a in args))
    with jax.enable_x64(True):
        (f64, t64, u64), _ = jit_scan(*(jnp.asarray(a, jnp.float64) for a in args))
    assert t32.dtype == jnp.float32 and t64.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(f32), np.asarray(f64))
    np.testing.assert_array_equal(np.asarray(u32), np.asarray(u64))
    f = np.asarray(f64)
    np.testing.assert_allclose(np.asarray(t32)[f], np.asarray(t64)[f], atol=5e-3)


def test_exact_scan_vmap_equals_loop_and_jit_equals_eager():
    t, level = traces(2, 7)
    log_i, tt = jnp.asarray(level, jnp.float32), jnp.asarray(t, jnp.float32)
    c_on = jnp.linspace(0.1, 0.25, 7)
    c_off = jnp.linspace(0.2, 0.12, 7)
    eta = jnp.asarray(25.0)

    def one_pixel(trace, on, off):
        out, _ = exact_events_scan(trace[:, None], tt, on[None], off[None], eta)
        return jax.tree.map(lambda a: a[:, 0], out)

    vmapped = jax.vmap(one_pixel, in_axes=(1, 0, 0))(log_i, c_on, c_off)
    eager, _ = exact_events_scan(log_i, tt, c_on, c_off, eta)
    jitted, _ = jit_scan(log_i, tt, c_on, c_off, eta)
    for p in range(7):
        looped = one_pixel(log_i[:, p], c_on[p], c_off[p])
        for a, b, c, d in zip(looped, vmapped, eager, jitted):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[p])
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c)[:, p])
            np.testing.assert_array_equal(np.asarray(a), np.asarray(d)[:, p])


@pytest.mark.parametrize("mode", ["release", "event"])
def test_exact_scan_state_carries_over(mode):
    """Two calls joined by the returned state equal one call over the whole trace."""
    t, level = traces(3, 4)
    log_i, tt = jnp.asarray(level, jnp.float32), jnp.asarray(t, jnp.float32)
    c = jnp.full(4, 0.12)
    eta = jnp.asarray(40.0)
    whole, _ = exact_events_scan(log_i, tt, c, c, eta, reset_mode=mode)
    k = 173
    first, state = exact_events_scan(
        log_i[: k + 1], tt[: k + 1], c, c, eta, reset_mode=mode
    )
    second, _ = exact_events_scan(log_i[k:], tt[k:], c, c, eta, state, reset_mode=mode)
    for a, b1, b2 in zip(whole, first, second):
        np.testing.assert_array_equal(np.asarray(a), np.concatenate([b1, b2]))


def test_exact_scan_refractory_and_polarity():
    t, level = traces(4, 8, n_t=800, dt=5.0)
    (fired, tc, up), _ = exact_events_scan(
        jnp.asarray(level, jnp.float32),
        jnp.asarray(t, jnp.float32),
        jnp.full(8, 0.1),
        jnp.full(8, 0.1),
        jnp.asarray(60.0),
    )
    fired, tc, up = np.asarray(fired), np.asarray(tc, np.float64), np.asarray(up)
    for p in range(8):
        times = tc[fired[:, p], p]
        assert np.all(np.diff(times) >= 60.0 - 1e-3)
        # ON events where the level rose over the step, OFF where it fell.
        steps = np.nonzero(fired[:, p])[0]
        rise = level[steps + 1, p] > level[steps, p]
        np.testing.assert_array_equal(up[steps, p], rise)
    # Event times lie inside their step.
    steps, pix = np.nonzero(fired)
    assert np.all(tc[steps, pix] >= t[steps] - 1e-3)
    assert np.all(tc[steps, pix] <= t[steps + 1] + 1e-3)


def test_flat_trace_never_fires():
    (fired, _, _), _ = exact_events_scan(
        jnp.full((50, 3), -2.0),
        jnp.arange(50.0),
        jnp.full(3, 0.15),
        jnp.full(3, 0.15),
        jnp.asarray(1.0),
    )
    assert not np.any(np.asarray(fired))


# --- soft model: convergence to the exact scan ---------------------------------------


def hard(fired, up):
    f, u = np.asarray(fired), np.asarray(up)
    return (f & u).astype(np.float64), (f & ~u).astype(np.float64)


def rig_traces(spectra_fine, rig):
    """log(I + ε) over one sweep of one column (default offsets τx = 0), (t, p)."""
    t = sweep_times_us(rig)
    a = column_time_table(rig, band_table(rig), t, jnp.zeros((), t.dtype))
    inten = a @ jnp.asarray(spectra_fine, t.dtype).T + rig.baseline_rel
    return t, jnp.log(inten + rig.log_eps)


def spectra_set(rig):
    wl = rig.grid.fine_centres_nm
    return np.stack(
        [
            np.full(wl.size, 0.9),
            np.full(wl.size, 0.2),
            0.1 + 0.8 * np.exp(-0.5 * ((wl - 550.0) / 40.0) ** 2),
            np.zeros(wl.size),
            np.full(wl.size, 1.0),
            np.where(np.abs(wl - 620.0) < 2.5, 1.0, 0.0),  # a 5 nm laser line
        ]
    )


TEMPERATURES = [0.1, 0.03, 0.01, 1e-3, 1e-4, 1e-6]


@pytest.fixture(scope="module")
def soft_vs_exact():
    """Per-step L1 distance between soft and exact counts, by temperature (float64)."""
    with jax.enable_x64(True):
        rig = Rig(threshold_sigma=0.0)
        t, log_i = rig_traces(spectra_set(rig), rig)
        thr_on = jnp.asarray([0.15, 0.13, 0.17, 0.15, 0.14, 0.16])
        thr_off = jnp.asarray([0.15, 0.14, 0.16, 0.15, 0.17, 0.12])
        (fired, _, up), _ = exact_events_scan(
            log_i, t, thr_on, thr_off, rig.refractory_us
        )
        on_h, off_h = hard(fired, up)
        soft = jax.jit(
            lambda temp: soft_event_counts(
                log_i, t, thr_on, thr_off, rig.refractory_us, temperature=temp
            )
        )
        dist, totals = {}, {}
        for temp in TEMPERATURES:
            on, off = (np.asarray(a) for a in soft(jnp.asarray(temp)))
            assert np.all((on >= 0) & (on <= 1) & (off >= 0) & (off <= 1))
            dist[temp] = np.abs(on - on_h).sum() + np.abs(off - off_h).sum()
            totals[temp] = (on.sum(0), off.sum(0))
    return dist, totals, (on_h.sum(0), off_h.sum(0))


def test_soft_counts_converge_to_exact(soft_vs_exact):
    dist, totals, (on_h, off_h) = soft_vs_exact
    n_events = on_h.sum() + off_h.sum()
    assert n_events > 60
    d = np.array([dist[k] for k in TEMPERATURES])
    assert np.all(np.diff(d) < 0), d
    # At a tiny temperature the soft scan is the exact one, step for step.
    assert d[-1] < 1e-3 * n_events
    assert d[-2] < 0.05 * n_events
    on, off = totals[1e-6]
    np.testing.assert_allclose(on, on_h, atol=1e-3)
    np.testing.assert_allclose(off, off_h, atol=1e-3)
    # A black pixel fires in neither model.
    assert on_h[3] == off_h[3] == 0 and totals[1e-3][0][3] < 1e-6


@pytest.mark.parametrize("x64", [False, True])
def test_soft_release_keeps_released_reference(x64):
    """A release that falls τ_t before a step boundary is split over two steps; the
    pixels released first must take the level at their release as reference, not a
    blend with the blind pixels' stale pre-event reference.

    A ramp of slope 0.01/µs on a 10 µs grid with C = 0.15 and η = 14.95 µs fires at
    15, 44.95 and 74.9 µs (mid-step) and releases 0.05 µs before a grid time.
    """
    with jax.enable_x64(x64):
        t = jnp.arange(0.0, 201.0) * 10.0
        log_i = jnp.minimum(0.01 * t, 0.9)[:, None]
        c, eta = jnp.asarray([0.15]), jnp.asarray(14.95)
        (fired, tc, up), _ = exact_events_scan(log_i, t, c, c, eta)
        on_h, off_h = hard(fired, up)
        np.testing.assert_allclose(
            np.asarray(tc)[np.asarray(fired)], [15.0, 44.95, 74.9], atol=1e-3
        )
        on, off = soft_event_counts(log_i, t, c, c, eta, temperature=1e-3)
    assert np.abs(np.asarray(on) - on_h).sum() < 1e-3
    assert np.abs(np.asarray(off) - off_h).sum() < 1e-3


def test_soft_float32_agrees_with_float64():
    rig32 = Rig(threshold_sigma=0.0)
    t32, l32 = rig_traces(spectra_set(rig32), rig32)
    c = jnp.full(6, 0.15)
    on32, off32 = soft_event_counts(
        l32, t32, c, c, rig32.refractory_us, temperature=0.05
    )
    with jax.enable_x64(True):
        rig64 = Rig(threshold_sigma=0.0)
        t64, l64 = rig_traces(spectra_set(rig64), rig64)
        c = jnp.full(6, 0.15)
        on64, off64 = soft_event_counts(
            l64, t64, c, c, rig64.refractory_us, temperature=0.05
        )
    assert on32.dtype == jnp.float32 and on64.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(on32), np.asarray(on64), atol=2e-3)
    np.testing.assert_allclose(np.asarray(off32), np.asarray(off64), atol=2e-3)
    np.testing.assert_allclose(
        np.asarray(on32).sum(0), np.asarray(on64).sum(0), rtol=1e-3, atol=1e-3
    )


# --- soft model: gradients with respect to the rig -----------------------------------

GRAD_PARAMS = [
    "beta_nm_per_rad",
    "fwhm_nm",
    "column_offsets_us",
    "baseline_rel",
    "threshold_on",
    "threshold_off",
    "sweep_start_nm",
]


def soft_loss(params, rig, spectra, temperature):
    """A smooth summary of the expected events of a few pixels of one column: the
    count-weighted mean time of ON minus OFF events plus the ON count."""
    r = rig.with_leaves(**params)
    t = sweep_times_us(r)
    table = band_table(r, fwhm_bound_nm=30.0)
    a = column_time_table(r, table, t, r.column_offsets_us[0])
    inten = a @ spectra.T + r.baseline_rel
    log_i = jnp.log(jnp.maximum(inten, 0.0) + r.log_eps)
    n = spectra.shape[0]
    on, off = soft_event_counts(
        log_i,
        t,
        r.threshold_on * jnp.ones(n),
        r.threshold_off * jnp.ones(n),
        r.refractory_us,
        temperature=temperature,
    )
    w = t[1:, None] / r.period_us
    return jnp.sum((on - off) * w) + 0.1 * jnp.sum(on)


@pytest.fixture(scope="module")
def soft_grad_fns():
    with jax.enable_x64(True):
        rig = Rig(column_offsets_us=[-1500.0], threshold_sigma=0.0)
        f = jax.jit(functools.partial(soft_loss, rig=rig, temperature=0.05))
        g = jax.jit(jax.grad(f))
        p0 = {k: getattr(rig, k) for k in GRAD_PARAMS}
        spectra = jnp.asarray(spectra_set(rig))
        # Compile both inside x64 so the tests below reuse them.
        f(p0, spectra=spectra)
        g(p0, spectra=spectra)
    return rig, f, g, p0, spectra


# Small steps: with few events (C = 0.5) or a narrow band the loss bends quickly.
FD_STEP = {
    "beta_nm_per_rad": 1e-5,
    "fwhm_nm": 1e-5,
    "column_offsets_us": 1e-3,
    "baseline_rel": 1e-4,  # relative to c
    "threshold_on": 1e-6,
    "threshold_off": 1e-6,
    "sweep_start_nm": 1e-5,
}


@pytest.mark.parametrize(
    "point, names",
    [
        ({}, GRAD_PARAMS),
        (
            {"threshold_on": 0.05, "threshold_off": 0.05},
            ["threshold_on", "threshold_off", "beta_nm_per_rad"],
        ),
        (
            {"threshold_on": 0.5, "threshold_off": 0.5},
            ["threshold_on", "threshold_off", "beta_nm_per_rad"],
        ),
        ({"baseline_rel": 1e-9}, ["baseline_rel", "beta_nm_per_rad"]),
        ({"fwhm_nm": 5.0}, ["fwhm_nm", "beta_nm_per_rad"]),
    ],
    ids=["default", "thr0.05", "thr0.5", "c1e-9", "fwhm5"],
)
def test_soft_gradients_match_finite_differences(soft_grad_fns, point, names):
    rig, f, g, p0, spectra = soft_grad_fns
    with jax.enable_x64(True):
        p = {k: jnp.asarray(point.get(k, v), jnp.float64) for k, v in p0.items()}
        grad = g(p, spectra=spectra)
        for k in names:
            h = FD_STEP[k] * (float(p[k]) if k == "baseline_rel" else 1.0)
            fd = (
                float(f({**p, k: p[k] + h}, spectra=spectra))
                - float(f({**p, k: p[k] - h}, spectra=spectra))
            ) / (2 * h)
            gk = float(jnp.sum(grad[k]))
            assert np.isfinite(gk), k
            np.testing.assert_allclose(gk, fd, rtol=2e-3, atol=1e-6, err_msg=k)


@pytest.mark.parametrize(
    "point",
    [
        {"baseline_rel": 0.0},
        {"baseline_rel": 0.0, "threshold_on": 0.05, "threshold_off": 0.05},
        {"baseline_rel": 1e-12, "threshold_on": 0.5, "threshold_off": 0.5},
        {"fwhm_nm": 1.0},
    ],
)
def test_soft_gradients_finite_at_hard_points(soft_grad_fns, point):
    rig, f, g, p0, spectra = soft_grad_fns
    with jax.enable_x64(True):
        p = {k: jnp.asarray(point.get(k, v), jnp.float64) for k, v in p0.items()}
        assert np.isfinite(float(f(p, spectra=spectra)))
        grad = {k: np.asarray(v) for k, v in g(p, spectra=spectra).items()}
    for k in GRAD_PARAMS:
        assert np.all(np.isfinite(grad[k])), k
    assert abs(grad["beta_nm_per_rad"].sum()) > 0


def test_soft_gradients_finite_exactly_at_threshold():
    """A trace whose level lands exactly on reference + C, and a pixel at zero
    intensity (log ε), in float32 and at a low temperature."""
    t = jnp.arange(0.0, 60.0) * 10.0
    bump = 0.3 * jnp.exp(-0.5 * ((t - 300.0) / 80.0) ** 2)
    exact_peak = bump - bump[0]
    log_i = jnp.stack([exact_peak, jnp.full_like(t, jnp.log(1e-5))], -1)

    def loss(log_i, c):
        on, off = soft_event_counts(log_i, t, c, c, jnp.asarray(20.0), temperature=1e-4)
        return jnp.sum(on * t[1:, None]) + jnp.sum(off)

    c = jnp.asarray([float(jnp.max(exact_peak)), 0.15])
    gl, gc = jax.grad(loss, argnums=(0, 1))(log_i, c)
    assert np.all(np.isfinite(np.asarray(gl))) and np.all(np.isfinite(np.asarray(gc)))
    # Exactly on the threshold the sigmoid sits at one half.
    on, _ = soft_event_counts(log_i, t, c, c, jnp.asarray(20.0), temperature=1e-4)
    np.testing.assert_allclose(float(jnp.max(on[:, 0])), 0.5, atol=1e-3)
