"""Calibration: residual gradients, recovery of a perturbed rig, bad input, white gains."""

import json
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev

H, W = 12, 8  # 6 gray stripes of 2 rows, 8 columns


def _true_rig(width=W, **kw):
    base = np.asarray(ev.Rig().column_offsets(width), np.float64)
    wiggle = 3.0 * np.sin(np.arange(width) / 2.0)
    cfg = dict(
        threshold_on=0.18,
        threshold_off=0.125,
        beta_nm_per_rad=185 * 1.07,
        baseline_rel=0.034,
        column_offsets_us=(base + 5.0 + wiggle).tolist(),
    )
    cfg.update(kw)
    return ev.Rig(**cfg)


@pytest.fixture(scope="module")
def capture():
    truth = _true_rig()
    chart = ev.load_scene("gray-chart", (H, W))
    events, info = ev.simulate(chart, truth, sweeps=2, key=jr.key(11), return_info=True)
    return truth, chart, events, info


@pytest.fixture(scope="module")
def fitted(capture):
    truth, chart, events, info = capture
    return ev.calibrate(events, chart, ev.Rig(), rows_per_label=None)


def test_recovers_a_perturbed_rig(capture, fitted):
    truth, _, _, info = capture
    rig = fitted.rig
    # Population thresholds: the mean of this sensor's per-pixel thresholds.
    assert float(rig.threshold_on) == pytest.approx(info.threshold_on.mean(), rel=0.01)
    assert float(rig.threshold_off) == pytest.approx(
        info.threshold_off.mean(), rel=0.01
    )
    assert float(rig.beta_nm_per_rad) == pytest.approx(
        float(truth.beta_nm_per_rad), rel=0.005
    )
    assert float(rig.baseline_rel) == pytest.approx(float(truth.baseline_rel), rel=0.02)
    tau_err = np.asarray(rig.column_offsets_us) - np.asarray(truth.column_offsets_us)
    assert np.sqrt(np.mean(tau_err**2)) < 2.0  # µs
    spread = info.threshold_on.std()
    assert (
        np.sqrt(np.mean((fitted.threshold_on_map - info.threshold_on) ** 2))
        < 0.2 * spread
    )
    assert (
        np.sqrt(np.mean((fitted.threshold_off_map - info.threshold_off) ** 2))
        < 0.2 * spread
    )
    assert fitted.rms_residual < 0.1 * fitted.rms_residual_initial
    # The cut-off was fitted, and an ideal sensor's counts as none.
    assert rig.effects.photoreceptor_hz == 0.0
    assert fitted.calibration.report["photoreceptor"].startswith("fitted")


def test_residual_gradients_match_finite_differences(capture):
    truth, chart, events, _ = capture
    with jax.enable_x64(True):
        rig = _true_rig(threshold_sigma=0.0).astype(jnp.float64)
        data = ev.calibration.chart_data(events, chart, rig, rows_per_label=1)

        def loss(r):
            res = ev.calibration.chart_residuals(r, data)
            return jnp.sum(res**2)

        grad = eqx.filter_grad(loss)(rig)
        checks = {
            "beta_nm_per_rad": (lambda r: r.beta_nm_per_rad, 1e-4),
            "threshold_on": (lambda r: r.threshold_on, 1e-7),
            "baseline_rel": (lambda r: r.baseline_rel, 1e-8),
            "fwhm_nm": (lambda r: r.fwhm_nm, 1e-5),
        }
        for name, (where, h) in checks.items():
            v = where(rig)
            fd = (
                loss(eqx.tree_at(where, rig, v + h))
                - loss(eqx.tree_at(where, rig, v - h))
            ) / (2 * h)
            assert float(where(grad)) == pytest.approx(float(fd), rel=1e-4, abs=1e-6), (
                name
            )
        # One column offset and one camera-response sample.
        g_tau = float(grad.column_offsets_us[3])
        h = 1e-3
        tp = rig.column_offsets_us.at[3].add(h)
        tm = rig.column_offsets_us.at[3].add(-h)
        fd = (
            loss(eqx.tree_at(lambda r: r.column_offsets_us, rig, tp))
            - loss(eqx.tree_at(lambda r: r.column_offsets_us, rig, tm))
        ) / (2 * h)
        assert g_tau == pytest.approx(float(fd), rel=1e-4, abs=1e-6)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grad))


def test_profiled_residuals_derivative_is_the_automatic_one(capture):
    """The per-pixel profiled residuals' derivative is written out (a custom JVP, for
    speed): it must equal the automatic derivative of the plain formula, also on rows
    without events of one polarity or with every log step 0; and a traced
    `per_pixel` (one program for both fit stages) gives the static answers."""
    from evhsi_jax._calibrate import _chart

    _, chart, events, _ = capture

    def plain(d, pos, neg):  # the formula before the JVP was written out
        def inv_c(sel, sign):
            num = jnp.sum(jnp.where(sel, sign * d, 0.0), 1, keepdims=True)
            den = jnp.sum(jnp.where(sel, d * d, 0.0), 1, keepdims=True)
            ok = den > 0
            return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)

        return jnp.where(pos, inv_c(pos, 1.0), jnp.where(neg, inv_c(neg, -1.0), 0.0))

    with jax.enable_x64(True):
        key1, key2, key3 = jr.split(jr.key(5), 3)
        d = jr.normal(key1, (6, 9))
        pol = jnp.where(jr.bernoulli(key2, 0.5, (6, 9)), 1.0, -1.0)
        mask = jnp.ones((6, 9), bool).at[:, 7:].set(False)
        pol = pol.at[1].set(1.0).at[2].set(-1.0)  # only ON / only OFF events
        d = d.at[3].set(0.0)  # every step 0: no threshold, no derivative
        pos, neg = mask & (pol > 0), mask & (pol < 0)
        for key in jr.split(key3, 3):
            t = jr.normal(key, d.shape)
            want = jax.jvp(lambda x: plain(x, pos, neg), (d,), (t,))
            got = jax.jvp(
                lambda x: _chart._own_inverse_thresholds(
                    x, pos.astype(x.dtype), neg.astype(x.dtype)
                ),
                (d,), (t,),
            )  # fmt: skip
            for a, b in zip(got, want, strict=True):
                np.testing.assert_allclose(
                    np.where(mask, a, 0.0), np.where(mask, b, 0.0), rtol=1e-12,
                    atol=1e-14,
                )  # fmt: skip

        rig = _true_rig().astype(jnp.float64)
        data = ev.calibration.chart_data(events, chart, rig, rows_per_label=1)
        for flag in (False, True):
            fixed = ev.calibration.chart_residuals(rig, data, per_pixel=flag)
            traced = jax.jit(
                lambda f: ev.calibration.chart_residuals(rig, data, per_pixel=f)
            )(jnp.asarray(flag))
            # (jit against eager arithmetic: d·u − σ cancels to ~1e-13)
            np.testing.assert_allclose(traced, fixed, rtol=0, atol=1e-11)

        # Reverse mode through the written-out derivative, against finite differences.
        def loss(r):
            res = ev.calibration.chart_residuals(r, data, per_pixel=True)
            return jnp.sum(res**2)

        grad = eqx.filter_grad(loss)(rig)
        for where, h in ((lambda r: r.beta_nm_per_rad, 1e-4),
                         (lambda r: r.baseline_rel, 1e-8)):  # fmt: skip
            v = where(rig)
            fd = (
                loss(eqx.tree_at(where, rig, v + h))
                - loss(eqx.tree_at(where, rig, v - h))
            ) / (2 * h)
            assert float(where(grad)) == pytest.approx(float(fd), rel=1e-4)


def test_gradients_finite_at_hard_points(capture):
    _, chart, events, _ = capture
    with jax.enable_x64(True):
        rig = _true_rig(baseline_rel=0.0, log_eps=1e-9).astype(jnp.float64)
        data = ev.calibration.chart_data(events, chart, rig, rows_per_label=1)
        grad = eqx.filter_grad(
            lambda r: jnp.sum(ev.calibration.chart_residuals(r, data) ** 2)
        )(rig)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grad))


def test_too_few_events_is_a_clear_error(capture):
    truth, chart, events, _ = capture
    few = events.take(np.arange(8))
    with pytest.raises(ValueError, match="too few"):
        ev.calibrate(few, chart, ev.Rig())


def test_degenerate_chart_is_a_clear_error(capture):
    truth, _, _, _ = capture
    flat = ev.load_scene("gray-chart", (H, W))
    one_level = ev.Scene(flat.palette[:1], flat.wavelengths_nm, np.zeros((H, W), int))
    events = ev.simulate(one_level, truth, sweeps=1, key=jr.key(0))
    with pytest.raises(ValueError, match="single reflectance level"):
        ev.calibrate(events, one_level, ev.Rig())


def test_chart_size_must_match(capture):
    _, _, events, _ = capture
    with pytest.raises(ValueError, match="chart is"):
        ev.calibrate(events, ev.load_scene("gray-chart", (H, W + 1)), ev.Rig())


def test_spectral_correction_recovers_a_channel_gain():
    rng = np.random.default_rng(0)
    ref = np.linspace(0.3, 0.9, 72)
    gain = 1 + 0.1 * np.sin(np.arange(72) / 7)
    cube = ref * gain * (1 + 0.01 * rng.standard_normal((5, 6, 72)))
    f = ev.calibration.spectral_correction(cube, ref)
    np.testing.assert_allclose(f, gain, rtol=0.01)
    rig = ev.calibration.apply_spectral_correction(ev.Rig(), f)
    assert rig.channel_gain is not None and len(rig.channel_gain) == 72
    with pytest.raises(ValueError):
        ev.calibration.apply_spectral_correction(ev.Rig(), f[:10])


def test_cli_calibrate_writes_a_file_reconstruct_reads(tmp_path, capture):
    truth, chart, events, info = capture
    ev.write_events(tmp_path / "gray.npz", events)
    evhsi = [sys.executable, "-m", "evhsi_jax.cli"]
    out = subprocess.run(
        [
            *evhsi,
            "calibrate",
            str(tmp_path / "gray.npz"),
            "--out",
            str(tmp_path / "c.json"),
        ],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    # The band profile: fitted (no band_profile in --init), said and written.
    assert "band profile" in out.stdout and ": FWHM" in out.stdout
    assert "fitted: FWHM" in out.stdout
    cfg = json.loads((tmp_path / "c.json").read_text())
    assert cfg["threshold_map"] == "c_thresholds.npz"
    assert cfg["band_profile"] is not None and cfg["calibration"]["band"] == "profile fitted"
    # Two sweeps: the mirror's speed per sweep is not measured (3 or more are needed).
    assert "mirror speed" in out.stdout and "not measured (one speed)" in out.stdout
    assert cfg["calibration"]["sweep_speed"] == "not measured (one speed)"
    assert cfg["calibration"]["chart_sweep_speeds"] is None
    cal = ev.load_calibration(tmp_path / "c.json")
    on = cal.threshold_on
    assert on.shape == (H, W) and cal.hot_pixels.shape == (H, W)
    assert (
        np.sqrt(np.mean((on - info.threshold_on) ** 2)) < 0.2 * info.threshold_on.std()
    )
    bad = subprocess.run(
        [
            *evhsi,
            "calibrate",
            str(tmp_path / "nope.npz"),
            "--out",
            str(tmp_path / "d.json"),
        ],
        capture_output=True,
        text=True,
    )
    assert bad.returncode != 0 and "Traceback" not in bad.stderr
    assert not (tmp_path / "d.json").exists()
    # A fit stopped by its step limit: refused, no file. (2 steps, as in
    # test_a_fit_that_did_not_converge_is_refused: the step limit is a static setting
    # of the solver's program, and the same limit lets both tests share one program.)
    short = subprocess.run(
        [*evhsi, "calibrate", str(tmp_path / "gray.npz"), "--out",
         str(tmp_path / "e.json"), "--max-steps", "2"],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert short.returncode == 2, short.stderr
    assert "did not converge" in short.stderr and len(short.stderr.splitlines()) == 1
    assert not (tmp_path / "e.json").exists()


def test_a_fit_that_did_not_converge_is_refused(capture):
    """Levenberg–Marquardt stopped by its step limit: no rig is returned (the CLI
    prints the one line and exits 2), even though the residual may look fine."""
    _, chart, events, _ = capture
    with pytest.raises(ValueError, match="did not converge"):
        ev.calibrate(events, chart, ev.Rig(), rows_per_label=None, max_steps=2)


def test_a_second_process_fits_from_stored_programs(capture, fitted, monkeypatch):
    """With the compilation cache on (this suite's default), the fit's solver stages
    and passes over the chart are stored programs (`call_exported`): a new process
    (empty memo, stored files) traces none of them and fits the same rig, bit for
    bit. (That a stored program's answers are those of the function called directly
    is `tests/test_cache.py`'s; checked by hand for this calibration too.)"""
    from evhsi_jax._base import _cache
    from evhsi_jax._calibrate import _chart, _fit

    if not _cache._ENABLED:
        pytest.skip("the compilation cache is off (EVHSI_CACHE_DIR=off)")
    _, chart, events, _ = capture
    monkeypatch.setattr(_cache, "_EXPORTED", {})  # a new process

    def untraced(*a, **k):
        raise AssertionError("traced although its program is stored")

    for mod, name in [(_fit, "_lm_stage"), (_fit, "_fit_residuals"),
                      (_chart, "_log_steps_jit")]:  # fmt: skip
        monkeypatch.setattr(mod, name, untraced)
    again = ev.calibrate(events, chart, ev.Rig(), rows_per_label=None)
    assert again.steps == fitted.steps
    for a, b in zip(
        jax.tree.leaves(again.rig), jax.tree.leaves(fitted.rig), strict=True
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(again.threshold_on_map, fitted.threshold_on_map)


def test_response_degree_zero_keeps_the_camera_response():
    """`response_degree=0` (D kept as given) has an empty correction basis."""
    from evhsi_jax._calibrate import _fit

    rig = _fit._with_column_offsets(ev.Rig(), W)
    basis = _fit._response_basis(rig, 0)
    assert basis.shape == (0, rig.grid.fine_centres_nm.shape[0])
    zero = jnp.zeros(())
    params = {"log_on": zero, "log_off": zero, "log_beta": zero, "log_c": zero,
              "tau": jnp.zeros((W,)), "resp": jnp.zeros((0,))}  # fmt: skip
    np.testing.assert_array_equal(
        np.asarray(_fit._apply(params, rig, basis).camera_response),
        np.asarray(rig.camera_response),
    )


def test_stopping_tests_end_where_tight_ones_do(capture, monkeypatch):
    """The Levenberg–Marquardt stages stop at tolerances the data resolve
    (`_fit.LM_TOL`), not at the tight ones used until 2026-11-27: they must not stop
    early. The fit with (1e-7, 1e-9) in both stages ends at the same rig (float64
    parameters within 1e-6 relative, τx within 1e-4 µs), in more steps; so does the
    global-only fit (`per_pixel=False`, one stage with the last stage's tolerances).
    With the band profile kept: its fit's slow tail is `test_band_fit.py`'s."""
    from evhsi_jax._calibrate import _fit

    _, chart, events, _ = capture
    tight_tol, default_tol = ((1e-7, 1e-9), (1e-7, 1e-9)), _fit.LM_TOL

    def fit(tol, per_pixel=True):
        monkeypatch.setattr(_fit, "LM_TOL", tol)
        init = ev.Rig()  # float32, as `fitted`'s (`ev.calibrate` converts it)
        with jax.enable_x64(True):
            return _fit._fit_chart_float64(
                events, chart, init.astype(jnp.float64), rows_per_label=None,
                per_pixel=per_pixel, fit_band=False,
            )  # fmt: skip

    def assert_same_globals(loose, tight):
        for k in ("threshold_on", "threshold_off", "beta_nm_per_rad", "baseline_rel"):
            a, b = float(getattr(loose.rig, k)), float(getattr(tight.rig, k))
            assert a == pytest.approx(b, rel=1e-6), k

    tight, loose = fit(tight_tol), fit(default_tol)
    default = ev.calibrate(events, chart, ev.Rig(), rows_per_label=None, fit_band=False)
    assert loose.steps == default.steps  # the default path (float32 rig)
    assert loose.steps < tight.steps
    assert_same_globals(loose, tight)
    np.testing.assert_allclose(
        loose.rig.column_offsets_us, tight.rig.column_offsets_us, rtol=0, atol=1e-4
    )
    np.testing.assert_allclose(
        loose.threshold_on_map, tight.threshold_on_map, rtol=1e-6
    )
    # Without per-pixel thresholds the one stage is the last: the final tolerances.
    assert_same_globals(fit(default_tol, False), fit(tight_tol, False))
