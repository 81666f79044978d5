"""The fused CPU backend (`backend="fused"`): the same problem as the JAX kernels, solved
in float64 from band segments — checked against the JAX path run in float64."""

import jax
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._base._numba import numba_available, readonly
from evhsi_jax._reconstruct import (
    ProblemConfig,
    _fused,
    _pipeline,
    _pixels,
)
from evhsi_jax._video._stream import _ReferenceCarry

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not available")

SIZE = (6, 8)


def _peaky_scene(rig, h, w, seed=0):
    """Narrow reflectance peaks on a dark floor: the bound x ≥ 0 is active."""
    rng = np.random.default_rng(seed)
    wl = np.asarray(rig.wavelengths_nm)
    centre = rng.uniform(wl[5], wl[-5], (h, w, 1))
    cube = 0.9 * np.exp(-0.5 * ((wl - centre) / 6.0) ** 2)
    return ev.Scene.from_cube(cube.astype(np.float32), wl)


@pytest.fixture(scope="module")
def captures():
    """Two sweeps with a curved sweep and per-pixel thresholds; one ColorChecker, one
    of narrow peaks."""
    rig = ev.Rig(sweep_curvature_nm=3.0)
    out = {}
    for name, scene in (
        ("colorchecker", ev.load_scene("colorchecker", SIZE)),
        ("peaks", _peaky_scene(rig, *SIZE)),
    ):
        events, info = ev.simulate(
            scene, rig, sweeps=2, key=jr.key(11), return_info=True
        )
        out[name] = (rig, events, info)
    return out


def _both(rig, events, info, cfg, **kw):
    # The mirror-speed estimate off unless asked for: it is a data-driven parameter,
    # estimated from a float32 or a float64 rig's table, and a factor that differs
    # in its last digits moves a narrow peak by a tenth of a degree.
    kw.setdefault("sweep_speed", "off")
    maps = dict(
        threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
    )
    fused, finfo = ev.reconstruct(
        events, rig, config=cfg, backend="fused", return_info=True, **maps, **kw
    )
    with jax.enable_x64(True):
        ref = ev.reconstruct(
            events, rig.astype(np.float64), config=cfg, backend="jax", **maps, **kw
        )
    return fused, finfo, ref


@pytest.mark.parametrize(
    "scene,cfg",
    [
        ("colorchecker", ProblemConfig()),
        ("peaks", ProblemConfig()),
        ("colorchecker", ProblemConfig(int_target="linear", spec_kind="dct")),
        ("peaks", ProblemConfig(int_target="peak", normalise=False)),
    ],
)
def test_fused_equals_float64_jax(captures, scene, cfg):
    rig, events, info = captures[scene]
    fused, finfo, ref = _both(rig, events, info, cfg)
    sam = ev.metrics.sam_map_deg(fused, ref)
    assert np.all(finfo.solved)
    assert sam.max() < 0.05, sam.max()
    assert np.abs(fused - ref).max() < 2e-3 * np.abs(ref).max()
    assert np.nanmax(finfo.kkt) < 1e-6


def test_speed_factors_move_the_times_alike(captures):
    # Given per-sweep mirror-speed factors, both backends read the events at the same
    # moved times (_sweep_speed.warp_times on the host's lists).
    rig, events, info = captures["colorchecker"]
    fused, finfo, ref = _both(rig, events, info, ProblemConfig(),
                              sweep_speed=[1.004, 0.997])  # fmt: skip
    assert ev.metrics.sam_map_deg(fused, ref).max() < 0.05
    np.testing.assert_array_equal(finfo.sweep_speed, [1.004, 0.997])
    plain, _, _ = _both(rig, events, info, ProblemConfig())
    assert ev.metrics.sam_map_deg(fused, plain).mean() > 0.3  # (the factors matter)


def test_carried_reference_through_the_photoreceptor():
    """With the photoreceptor pass, a sweep's first event refers to the level its
    pixel's last event of the sweep before left (the filter's response there under
    the spectrum solved for, read a period later on the recording's grid) instead of
    the baseline at the grid's first point. Per-sweep recordings of a noisy sensor
    (the pass with log-unit rows) then beat the same sweeps taken from the baseline,
    as on an ideal sensor; the JAX path reads it alike."""
    rig = ev.Rig.from_dict({"threshold_noise": 0.01})
    h, w = 12, 16
    scene = ev.load_scene("tcs", (h, w))
    events, info = ev.simulate(scene, rig, sweeps=3, key=jr.key(5), return_info=True)
    truth = scene.truth_cube(rig.grid)
    period, eta = float(rig.period_us), float(rig.refractory_us)
    kw = dict(threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off,
              sweep_speed="off", backend="fused")  # fmt: skip
    last = np.full(h * w, np.nan)
    gain = []
    for s in range(3):
        t0, t1 = int(round(s * period)), int(round((s + 1) * period))
        win = events.time_window(t0, t1)
        carried = ev.reconstruct(win, rig, t_start_us=t0, reference_us=(
            last + eta).reshape(h, w), **kw)  # fmt: skip
        plain = ev.reconstruct(win, rig, t_start_us=t0, **kw)
        gain.append(ev.evaluate(plain, truth)["sam_deg"]
                    - ev.evaluate(carried, truth)["sam_deg"])  # fmt: skip
        if s == 1:  # the JAX path (float64) reads the carried reference alike
            with jax.enable_x64(True):
                jx = ev.reconstruct(win, rig.astype(np.float64), t_start_us=t0,
                                    reference_us=(last + eta).reshape(h, w),
                                    **dict(kw, backend="jax"))  # fmt: skip
            assert ev.metrics.sam_map_deg(carried, jx).max() < 0.05
        np.fmax.at(last, win.y.astype(np.int64) * w + win.x, win.t_us + 0.5)
    assert gain[0] == 0.0  # (no earlier events: the same recording)
    assert min(gain[1:]) > 0.4, gain  # (0.69° and 0.58°; 0 before the fix)


def test_active_set_steps_match(captures):
    """The narrow peaks need active-set steps; the fused steps reach the same optimum
    (also with a carried reference per pixel, as the per-sweep path passes)."""
    rig, events, info = captures["peaks"]
    h, w = SIZE
    ref_us = np.where(np.arange(h * w).reshape(h, w) % 3 == 0, -4000.0, np.nan)
    fused, _, ref = _both(rig, events, info, ProblemConfig(), reference_us=ref_us)
    assert ev.metrics.sam_map_deg(fused, ref).max() < 0.05
    # Steps were needed: the unconstrained optimum has negative entries here.
    lists = _fused_lists(rig, events)
    prob = _fused.FusedProblem(
        rig, _pipeline.channel_table(rig), ProblemConfig(),
        _pipeline.solver_spec("auto"), w, np.asarray(rig.column_offsets(w)), 2,
    )  # fmt: skip
    counts, starts, t, s = lists
    sel = np.flatnonzero(counts)
    x, kkt, steps = _fused.solve_fused(
        prob, sel, starts, counts, t, s, np.zeros(h * w),
        info.threshold_on.reshape(-1), info.threshold_off.reshape(-1), threads=1,
    )  # fmt: skip
    assert steps.max() > 0 and np.all(steps >= 0)
    assert np.all(x >= 0) and np.all(kkt < 1e-6)
    x2, _, steps2 = _fused.solve_fused(
        prob, sel, starts, counts, t, s, np.zeros(h * w),
        info.threshold_on.reshape(-1), info.threshold_off.reshape(-1), threads=2,
    )  # fmt: skip
    np.testing.assert_array_equal(x, x2)  # threads split pixels, not sums
    np.testing.assert_array_equal(steps, steps2)


def _lanes_1_and_4(rig, events, info, sweeps):
    """The kernel's answers with one pixel at a time and with four side by side (the
    long rows in Q too, as the one-pixel kernel has them), on the pixels with events
    but the last one or two (a last group of three)."""
    h, w = SIZE
    noise = _pipeline.noise_model(rig)
    counts, starts, t, s = _fused_lists(rig, events, noise, sweeps)
    sel = np.flatnonzero(counts)
    sel = sel[: 4 * ((sel.size - 3) // 4) + 3]
    answers = []
    for lanes in (1, 4):
        prob = _fused.FusedProblem(
            rig, _pipeline.channel_table(rig), ProblemConfig(),
            _pipeline.solver_spec("auto"), w, np.asarray(rig.column_offsets(w)),
            sweeps, noise, lanes=lanes, long_rows=False,
        )  # fmt: skip
        answers.append(_fused.solve_fused(
            prob, sel, starts, counts, t, s, np.zeros(h * w),
            info.threshold_on.reshape(-1), info.threshold_off.reshape(-1), threads=1,
        ))  # fmt: skip
    return answers


def _assert_same_answers(answers):
    # The lanes group their dot products differently (the last bits of each differ);
    # an ill-conditioned pixel (cond(Q) ~1e8) amplifies that up to ~1e-8: the
    # answers must agree far inside it. (1.5e-11 × max on the peaks since the bands'
    # trim of 1e-7, whose narrower envelope changes where the sums start.)
    (x1, kkt1, steps1), (x4, kkt4, steps4) = answers
    np.testing.assert_array_equal(steps4, steps1)
    np.testing.assert_allclose(x4, x1, rtol=0, atol=1e-10 * np.abs(x1).max())
    np.testing.assert_allclose(kkt4, kkt1, rtol=0, atol=1e-9)


@pytest.mark.parametrize("scene", ["colorchecker", "peaks"])
def test_lanes_equal_one_pixel_at_a_time(captures, scene):
    """Four pixels solved side by side (the default) give the one-pixel kernel's
    answers and steps, also for a last group of fewer than four and for pixels that
    need active-set steps (peaks)."""
    rig, events, info = captures[scene]
    answers = _lanes_1_and_4(rig, events, info, 2)
    steps1 = answers[0][2]
    assert np.all(steps1 >= 0) and (steps1.max() > 0) == (scene == "peaks")
    _assert_same_answers(answers)


@pytest.mark.parametrize("noisy", [False, True])
def test_long_rows_by_woodbury_give_the_same_optimum(noisy):
    """A sweep's first event refers to the previous sweep's last one (blue against
    red): rows that span the spectrum. The lanes leave them out of Q and add them by
    the Woodbury identity (`long_rows`, the default); the answers are those with the
    rows in Q, to the rounding an ill-conditioned pixel amplifies, the active-set
    steps the same, every KKT residual small — on the second sweep of a capture cut
    per sweep (the reference carried as the per-sweep path carries it), with and
    without the noise model's weights and reweighting, and on pixels that need
    active-set steps (leaving the lanes, they take their long rows along)."""
    h, w = SIZE
    kw = dict(threshold_noise=0.01, timestamp_jitter_us=5.0) if noisy else {}
    rig = ev.Rig(**kw)
    noise = _pipeline.noise_model(rig)
    period = float(rig.period_us)
    # Narrow peaks at both ends of the spectrum on a dark floor: each pixel's first
    # event is blue and its reference red, and the bound x ≥ 0 is active.
    wl = np.asarray(rig.wavelengths_nm)
    rng = np.random.default_rng(2)
    ends = (rng.uniform(wl[3], wl[12], (*SIZE, 1)), rng.uniform(wl[-12], wl[-3], (*SIZE, 1)))
    two = sum(0.9 * np.exp(-0.5 * ((wl - c) / 6.0) ** 2) for c in ends)
    two_peaks = ev.Scene.from_cube(two.astype(np.float32), wl)
    for scene in (ev.load_scene("colorchecker", SIZE), two_peaks):
        events, info = ev.simulate(scene, rig, sweeps=2, key=jr.key(5), return_info=True)
        t = np.asarray(events.t_us)
        t0 = int(round(period))
        second = events.take(np.flatnonzero((t >= t0) & (t < 2 * t0)))
        kept, _, _ = _pipeline.screen_events(second, rig, t0, noise, 1, None)
        counts, starts, t_rel, sgn = _pixels.pixel_lists(kept, t0)
        carry = _ReferenceCarry(h, w, float(rig.refractory_us), rig.column_offsets(w),
                                period)  # fmt: skip
        carry.add(events.take(np.flatnonzero(t < t0)))
        ref = carry.reference_us()
        lead = _pipeline._reference_lead_us(ref, t0, period, h, w)
        assert np.count_nonzero(lead) > h * w // 2
        sel = np.flatnonzero(counts)
        args = (starts, counts, t_rel, sgn, lead, info.threshold_on.reshape(-1),
                info.threshold_off.reshape(-1))  # fmt: skip
        answers = []
        for long_rows in (False, True):
            prob = _fused.FusedProblem(
                rig, _pipeline.channel_table(rig), ProblemConfig(),
                _pipeline.solver_spec("auto"), w, np.asarray(rig.column_offsets(w)), 1,
                noise, long_rows=long_rows,
            )  # fmt: skip
            answers.append(_fused.solve_fused(prob, sel, *args, threads=1))
        (x0, kkt0, steps0), (x1, kkt1, steps1) = answers
        np.testing.assert_array_equal(steps1, steps0)
        assert np.all(steps1 >= 0)
        assert not np.array_equal(x1, x0)  # the other route was taken
        sam = ev.metrics.sam_map_deg(x1[None], x0[None])
        assert np.nanmax(sam) < 0.02, np.nanmax(sam)
        np.testing.assert_allclose(x1, x0, rtol=0, atol=1e-3 * np.abs(x0).max())
        assert np.all(kkt1 < max(1e-9, 2 * kkt0.max()))
    assert steps0.max() > 0  # the peaks needed active-set steps


def test_lanes_equal_one_pixel_at_a_time_noise_aware():
    """The same with the noise-aware problem of the realistic preset: each pixel of
    a group keeps its own event rows, photoreceptor pass and reweighting."""
    rig = ev.Rig(sensor="realistic")
    scene = ev.load_scene("colorchecker", SIZE)
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(7), return_info=True)
    _assert_same_answers(_lanes_1_and_4(rig, events, info, 1))


def test_photoreceptor_path_answers_in_the_callers_order():
    """With the photoreceptor rows the kernel takes the pixels column by column
    (`FusedProblem.kernel_order`); pixels handed over in image order get their
    answers moved back, pixels already in column order (`reconstruct`'s case) none:
    the same answer per pixel either way, bit for bit."""
    h, w = SIZE
    rig = ev.Rig(sensor="realistic")
    scene = ev.load_scene("colorchecker", SIZE)
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(7), return_info=True)
    noise = _pipeline.noise_model(rig)
    counts, starts, t, s = _fused_lists(rig, events, noise, 1)
    prob = _fused.FusedProblem(
        rig, _pipeline.channel_table(rig), ProblemConfig(),
        _pipeline.solver_spec("auto"), w, np.asarray(rig.column_offsets(w)), 1, noise,
    )  # fmt: skip
    sel = np.flatnonzero(counts)
    order = prob.kernel_order(sel)
    assert prob.lowpass and order is not None
    assert prob.kernel_order(sel[order]) is None  # already in the kernel's order
    args = (starts, counts, t, s, np.zeros(h * w), info.threshold_on.reshape(-1),
            info.threshold_off.reshape(-1))  # fmt: skip
    x, kkt, steps = _fused.solve_fused(prob, sel, *args, threads=1)
    xc, kktc, stepsc = _fused.solve_fused(prob, sel[order], *args, threads=1)
    np.testing.assert_array_equal(x[order], xc)
    np.testing.assert_array_equal(kkt[order], kktc)
    np.testing.assert_array_equal(steps[order], stepsc)
    # Straight into a cube's rows (`out`), on two threads (blocks of 16 pixels, some
    # of them not consecutive in the image), from either order: the same answers
    # in float32, every other row untouched.
    for pixels in (sel, sel[order]):
        cube = np.full((h * w, prob.channels), -7.0, np.float32)
        kkt_all = np.full(h * w, -7.0, np.float32)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(_fused, "BLOCK_PIXELS", 16)
            xo, ko, so = _fused.solve_fused(
                prob, pixels, *args, threads=2, out=(cube, kkt_all)
            )  # fmt: skip
        assert xo is None and ko is None
        at = np.searchsorted(sel, pixels)
        np.testing.assert_array_equal(so, steps[at])
        np.testing.assert_array_equal(cube[sel], x.astype(np.float32))
        np.testing.assert_array_equal(kkt_all[sel], kkt.astype(np.float32))
        rest = np.setdiff1d(np.arange(h * w), sel)
        assert np.all(cube[rest] == -7.0) and np.all(kkt_all[rest] == -7.0)


def test_lane_solver_flags_a_failed_lane():
    """`_solve_lanes` on three systems with different envelopes, in the lane layout
    over their union envelope (the fourth lane repeats the third): each lane's answer
    is its own system's solution, and only the lane whose matrix is not positive
    definite is marked failed."""
    from evhsi_jax._reconstruct import _fused_jit as jit

    m, rng = 12, np.random.default_rng(3)
    qms, qvs = np.zeros((4, m, m)), rng.normal(size=(4, m))
    firsts = np.zeros((4, m), np.int64)
    for lane, band in enumerate((2, 5, 11)):
        a = np.zeros((m, m))
        for i in range(m):
            lo = max(0, i - band)
            a[i, lo : i + 1] = rng.normal(size=i + 1 - lo)
            a[i, i] = 3.0 + band
        full = a @ a.T  # banded-envelope SPD (band² wide); lane 1 made indefinite
        if lane == 1:
            full[4, 4] = -1.0
        qms[lane] = np.tril(full)
        firsts[lane] = [
            np.flatnonzero(np.abs(full[i, : i + 1]) > 0)[0] for i in range(m)
        ]
    lanes = [0, 1, 2, 2]  # the lane layout: lane l of (i, j) at 4 (i m + j) + l
    ql = np.ascontiguousarray(qms[lanes].transpose(1, 2, 0)).ravel()
    qvl = np.ascontiguousarray(qvs[lanes].T).ravel()
    fu = firsts[:3].min(axis=0)
    lf, inv, xl = np.zeros(ql.size), np.zeros(4 * m), np.zeros(4 * m)
    ptr, fail = np.zeros(m, np.int64), np.zeros(4, bool)
    jit._solve_lanes(ql, qvl, fu, ptr, lf, inv, xl, fail, m)
    assert list(fail) == [False, True, False, False]
    for lane in (0, 2):
        full = qms[lane] + np.tril(qms[lane], -1).T
        want = -np.linalg.solve(full, qvs[lane])
        np.testing.assert_allclose(xl[lane::4], want, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(xl[3::4], xl[2::4])  # the repeated last system


def test_lane_photoreceptor_rows_equal_one_pixel_bit_for_bit():
    """`_lane_lowpass_rows` (a group's pixels of one column side by side) forms the
    photoreceptor model's event rows of `_lowpass_rows` to the last bit, for a group
    of three with one pixel left out (`todo`), pixels of different event counts and
    lags, over two sweeps, and with one pixel whose reference lies before the
    recording; the pixel left out keeps its rows untouched."""
    from evhsi_jax._reconstruct import _fused_jit as jit

    rig, w, sweeps = ev.Rig(sensor="realistic"), 8, 2
    prob = _fused.FusedProblem(
        rig, _pipeline.channel_table(rig), ProblemConfig(),
        _pipeline.solver_spec("auto"), w, np.asarray(rig.column_offsets(w)), sweeps,
        _pipeline.noise_model(rig),
    )  # fmt: skip
    # The kernel's inputs as the kernel gets them (read-only: the same compiled
    # helpers as the kernel's, not a second version of each).
    ro = {k: readonly(getattr(prob, k), getattr(prob, k).dtype)
          for k in ("par", "ipar", "table", "span_lo", "span_hi")}  # fmt: skip
    par, ipar, m = ro["par"], ro["ipar"], prob.channels
    n, period = int(ipar[jit.I_SAMPLES]), par[jit.P_PERIOD]
    span = prob.span_hi - prob.span_lo
    w_col = int(max(span.max(), 1)) + 8
    cspan, crow = np.zeros((n, 2), np.int64), np.zeros((n, w_col))
    jit._column_grid(
        float(prob.col_off[3]), par, ipar, ro["table"], ro["span_lo"], ro["span_hi"],
        cspan, crow,
    )  # fmt: skip
    rng = np.random.default_rng(5)
    g, kmax, nl = 4, 30, 3
    ks = np.array([30, 17, 24, 0])
    todo = np.array([True, False, True, False])
    xs = rng.uniform(0.05, 1.0, (g, m))
    trs, steps, wl = np.zeros((g, kmax)), np.zeros((g, kmax)), np.zeros((g, kmax))
    for p in range(g):
        trs[p, : ks[p]] = np.sort(rng.uniform(0.0, sweeps * period * 0.95, ks[p]))
        steps[p, : ks[p]] = rng.choice([-0.25, 0.2], ks[p])
        wl[p, : ks[p]] = rng.uniform(0.3, 1.0, ks[p])
    # Pixel 0's first reference lies before the recording (a carried one: read a
    # period later); pixel 2's does not.
    phases = np.array([-30.0, 12.0, 25.0, -5.0])
    nbuf, n_grid = 2 * kmax, sweeps * n + 1

    def rows():
        return (np.full((g, kmax, m), 7.0), np.zeros((g, kmax)),
                np.zeros((g, kmax), np.int64), np.zeros((g, kmax), np.int64))  # fmt: skip

    one, lane = rows(), rows()
    for p in range(nl):
        if todo[p]:
            jit._lowpass_rows(
                xs[p], trs[p], steps[p], wl[p], ks[p], phases[p], par, ipar, cspan,
                crow, np.zeros(m + 1), np.zeros((1, nbuf, m + 1)),
                np.zeros(n_grid, np.int64), np.zeros((2 * nbuf, 3), np.int64),
                np.zeros(2 * nbuf), np.zeros(1), *(a[p] for a in one),
                np.zeros((4, n_grid)),
            )  # fmt: skip
    jit._lane_lowpass_rows(
        todo, nl, xs, trs, steps, wl, ks, phases, par, ipar, cspan, crow,
        np.zeros(4 * (m + 1)), np.zeros((g, nbuf, m + 1)), np.zeros(n_grid, np.int64),
        np.zeros((2 * g * nbuf, 3), np.int64), np.zeros(2 * g * nbuf), *lane,
        np.zeros((4, 4 * n_grid)), np.zeros(4 * m), np.zeros(16),
    )  # fmt: skip
    for a, b in zip(one, lane):
        np.testing.assert_array_equal(a, b)
    assert np.all(lane[0][1] == 7.0)  # the pixel left out: untouched
    assert np.abs(lane[0][0, : ks[0]]).max() > 0  # rows were formed


def _fused_lists(rig, events, noise=None, sweeps=2):
    t0 = int(events.trigger_t_us[0])
    screened, _, _ = _pipeline.screen_events(events, rig, t0, noise, sweeps)
    from evhsi_jax._reconstruct._pixels import pixel_lists

    return pixel_lists(screened, t0)


def test_reweighting_median_is_numpys():
    """The robust reweighting's median (`_median`: insertion sort in a work buffer,
    no allocation) is `np.median`'s value to the bit, odd and even counts, ties."""
    from evhsi_jax._reconstruct import _fused_jit as jit

    rng = np.random.default_rng(3)
    buf = np.empty(64)
    for k in (1, 2, 3, 4, 17, 28, 64):
        for a in (rng.exponential(size=64), np.round(rng.uniform(0, 3, 64), 1)):
            before = a.copy()
            assert jit._median(a, k, buf) == np.median(a[:k])
            np.testing.assert_array_equal(a, before)  # left as it was


def test_failed_factorisation_falls_back(captures, monkeypatch):
    """A pixel the kernel reports as failed (steps −1) is re-solved by the JAX path."""
    rig, events, info = captures["colorchecker"]
    maps = dict(
        threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
    )
    good = ev.reconstruct(events, rig, backend="fused", **maps)
    real = _fused.solve_fused

    def failing(prob, sel, *a, **k):
        x, kkt, steps = real(prob, sel, *a, **k)
        if k.get("out") is None:
            x[::5] = np.nan
        else:  # the answers went into the cube's rows `sel`
            k["out"][0][sel[::5]] = np.nan
        steps[::5] = -1
        return x, kkt, steps

    monkeypatch.setattr(_pipeline, "solve_fused", failing)
    patched = ev.reconstruct(events, rig, backend="fused", **maps)
    assert np.all(np.isfinite(patched))
    assert (
        ev.metrics.sam_map_deg(patched, good).max() < 0.5
    )  # float32 JAX against float64 fused


def test_non_finite_answers_never_leave_reconstruct(captures, monkeypatch):
    """A pixel whose re-solve too comes out non-finite gets the no-event answer and
    kkt = inf (the cube's finiteness is checked by its minimum and maximum:
    `_all_finite`, which NaN, +inf and -inf each fail)."""
    assert _pipeline._all_finite(np.zeros((0, 3), np.float32))
    for v in (np.nan, np.inf, -np.inf):
        a = np.ones((4, 3), np.float32)
        assert _pipeline._all_finite(a)
        a[2, 1] = v
        assert not _pipeline._all_finite(a)
    rig, events, info = captures["colorchecker"]
    real = _fused.solve_fused

    def failing(prob, sel, *a, **k):
        x, kkt, steps = real(prob, sel, *a, **k)
        steps[:3] = -1
        return x, kkt, steps

    def nan_resolve(rig, table, cfg, spec, px, idx, sweeps, noise):
        m = _pipeline.channel_table(rig).values.shape[1]
        return np.full((idx.size, m), np.nan), np.zeros(idx.size)

    monkeypatch.setattr(_pipeline, "solve_fused", failing)
    monkeypatch.setattr(_pipeline, "_solve_robust_at", nan_resolve)
    cube, got = ev.reconstruct(
        events, rig, backend="fused", threshold_on_map=info.threshold_on,
        threshold_off_map=info.threshold_off, return_info=True,
    )  # fmt: skip
    assert np.all(np.isfinite(cube))
    flat = cube.reshape(-1, cube.shape[-1])
    first3 = np.flatnonzero(got.events.ravel())[:3]
    no_event = _pipeline._no_event_answer(rig, cube.shape[-1])
    np.testing.assert_allclose(flat[first3], np.broadcast_to(no_event, flat[first3].shape))
    assert np.all(np.isinf(got.kkt.ravel()[first3]))
    assert np.isfinite(got.kkt.ravel()[np.flatnonzero(got.events.ravel())[3:]]).all()


def test_backend_choice_and_refusals(captures):
    rig, events, _ = captures["colorchecker"]
    with pytest.raises(ValueError, match="backend must be one of"):
        ev.reconstruct(events, rig, backend="numba")
    with pytest.raises(ValueError, match="threads must be"):
        ev.reconstruct(events, rig, threads=0)
    with pytest.raises(ValueError, match="solver 'apg'"):
        ev.reconstruct(events, rig, backend="fused", solver="apg")
    # The CUDA kernel needs a CUDA GPU (the simulator's runs are in
    # test_cuda_kernel.py) and a float32 rig; auto never picks it here.
    with pytest.raises(ValueError, match="cuda backend cannot run.*(GPU|CUDA)"):
        ev.reconstruct(events, rig, backend="cuda")
    with jax.enable_x64(True), pytest.raises(ValueError, match="float64 rig"):
        ev.reconstruct(events, rig.astype(np.float64), backend="cuda")
    assert not _pipeline._use_cuda(
        "auto", False, _pipeline.solver_spec("auto"), ProblemConfig(), rig, None
    )
    assert _fused.fused_supported(
        _pipeline.solver_spec("auto"), ProblemConfig(lookup_order=3)
    ).startswith("lookup_order 3")
    # auto on a CPU: the fused kernel, the same cube as asking for it.
    np.testing.assert_array_equal(
        ev.reconstruct(events, rig), ev.reconstruct(events, rig, backend="fused")
    )


@pytest.mark.parametrize(
    "keys,sweeps",
    [
        # Noise weights, the dark-channel prior and the robust reweighting (Huber and
        # rejection of background events), no photoreceptor.
        (dict(threshold_noise=0.01, timestamp_jitter_us=5.0, noise_rate_hz=3.0), 1),
        # The realistic preset: also the photoreceptor's lag and its relinearised
        # model (Gauss–Newton pass), a skewed band, a curved sweep.
        (dict(sensor="realistic"), 2),
        # More than 4 sweeps: the passes run too (since 2026-11-29), the JAX path's
        # sub-batch shrunk to bound its photoreceptor grids (LOWPASS_SUB_SWEEPS).
        (dict(sensor="realistic"), 6),
    ],
)
def test_noise_aware_fused_equals_float64_jax(keys, sweeps):
    """With a sensor noise model the fused kernel solves the noise-aware problem of
    the JAX path (same weights, priors, reweighting and low-pass rows), and the
    search for stray events that follows it finds the same ones
    (tests/reconstruction/test_strays.py)."""
    rig = ev.Rig(**keys)
    assert _pipeline.noise_model(rig) is not None
    scene = ev.load_scene("colorchecker", SIZE)
    events, info = ev.simulate(scene, rig, sweeps=sweeps, key=jr.key(5),
                               return_info=True)  # fmt: skip
    fused, finfo, ref = _both(rig, events, info, ProblemConfig())
    assert finfo.stray_events >= 1  # (1, 3 and 4 in these captures)
    assert ev.metrics.sam_map_deg(fused, ref).max() < 0.05
    assert np.abs(fused - ref).max() < 2e-3 * np.abs(ref).max()
    assert np.all(np.isfinite(finfo.kkt[finfo.solved]))


def test_vectorised_exp_and_log_are_libm_within_an_ulp():
    """The photoreceptor rows' exp and log (`_fused_jit._exp_rows`, `_log_rows`:
    polynomials on the numbers' bits, so that LLVM vectorises them) against NumPy's
    over the ranges the rows use and beyond: within ~1 ulp (relative 2.3e-16 for
    exp, absolute 1.2e-16 or relative 4e-16 for log), exact at the powers of two,
    and exp clamped below at −700 (≈1e-304: a restart of the recursion, as 0)."""
    import numba

    from evhsi_jax._reconstruct import _fused_jit as jit

    @numba.njit
    def run(a, n):
        jit._exp_rows(a, 1, n)
        jit._log_rows(a, 3, 2, n)

    rng = np.random.default_rng(5)
    y = np.concatenate([rng.uniform(-700, 700, 40_000), -rng.uniform(0, 1e3, 20_000),
                        [0.0, -0.0, -1e-300, 1e-12, -460.5, -700.0, -745.0, -1e6]])  # fmt: skip
    x = np.concatenate([np.exp(rng.uniform(-700, 700, 40_000)),
                        rng.uniform(1e-4, 3.0, 20_000),
                        [1.0, 2.0, 0.5, 2.0**-1000, 2.0**1000, np.sqrt(2.0),
                         np.sqrt(0.5), np.nextafter(1.0, 2.0)]])  # fmt: skip
    a = np.zeros((4, y.size))
    a[1], a[3] = y, x
    run(a, y.size)
    want_exp = np.exp(np.maximum(y, -700.0))
    np.testing.assert_allclose(a[1], want_exp, rtol=2.5e-16, atol=0)
    want_log = np.log(x)
    err = np.abs(a[2] - want_log)
    assert np.all((err <= 1.2e-16) | (err <= 4e-16 * np.abs(want_log)))
    np.testing.assert_array_equal(a[2][-8:-3], np.log(x[-8:-3]))
    np.testing.assert_array_equal(a[3], x)  # the input row is kept


def test_one_compiled_kernel_for_float32_and_float64_rigs(captures):
    """A float64 rig's band table reaches the kernel as a NumPy view of a JAX array
    (read-only), a float32 rig's as a copy (writable): the kernel's inputs are made
    one array type (`_fused.kernel_inputs`), so numba compiles — and caches — the
    kernel once for both (it compiled a second one, ~20 s, before)."""
    from evhsi_jax._reconstruct import _fused_jit

    rig, events, _ = captures["colorchecker"]
    a = ev.reconstruct(events, rig, backend="fused")
    with jax.enable_x64(True):
        b = ev.reconstruct(events, rig.astype(np.float64), backend="fused")
    assert len(_fused_jit.solve_pixels.signatures) == 1
    assert len(_fused_jit._box_qp.signatures) <= 1  # (not compiled on a cache hit)
    assert ev.metrics.sam_map_deg(a, b).max() < 0.1  # (tables rounded differently)


def test_block_pixels_splits_work_evenly_within_bounds():
    """Blocks for the workers: a whole sweep in the largest blocks, a small image
    still in ~16 blocks per worker (never below the floor unless it has fewer
    pixels), and every pixel covered."""
    big = _fused.block_pixels(1280 * 720, 2)
    assert big == _fused.BLOCK_PIXELS
    small = _fused.block_pixels(96 * 144, 2)
    assert _fused.MIN_BLOCK_PIXELS <= small < _fused.BLOCK_PIXELS
    assert -(-96 * 144 // small) >= 2 * _fused.BLOCKS_PER_THREAD - 1
    assert _fused.block_pixels(10, 2) == _fused.MIN_BLOCK_PIXELS  # one block
    assert _fused.block_pixels(0, 1) >= 1
    for n, t in [(1, 1), (5000, 3), (10**6, 16)]:
        b = _fused.block_pixels(n, t)
        assert 1 <= b <= _fused.BLOCK_PIXELS and -(-n // b) * b >= n
