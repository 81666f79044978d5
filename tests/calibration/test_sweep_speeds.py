"""A mirror whose speed differs from sweep to sweep, seen in the gray chart: the
calibration measures each sweep's factor and fits the chart with every sweep read at
its own speed (`_chart.chart_sweep_speeds`, `_fit._fit_chart_float64(sweep_speeds=)`)."""

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax import calibration as C


def _robust_spread(f):
    return 1.4826 * np.median(np.abs(f - np.median(f)))


@pytest.fixture(scope="module")
def jittery():
    """A 16×24 chart recorded for 8 sweeps by a mirror with 0.3 % speed jitter."""
    chart = ev.load_scene("gray-chart", (16, 24))
    true = ev.Rig(sweep_rate_jitter=0.003)
    events, info = ev.simulate(chart, true, sweeps=8, key=jr.key(3), return_info=True)
    return chart, true, events, info


@pytest.fixture(scope="module")
def fits(jittery):
    chart, _, events, _ = jittery
    each = ev.calibrate(events, chart, ev.Rig())
    one = ev.calibrate(events, chart, ev.Rig(), sweep_speeds=None)  # (as before)
    return each, one


def test_each_sweeps_speed_is_measured_from_the_chart(jittery):
    chart, true, events, info = jittery
    sp = C.chart_sweep_speeds(events, chart, true, t_start_us=0)
    truth = info.speed_factor / info.speed_factor.mean()
    assert np.std(truth) > 0.002  # (the draw: factors apart by more than the bound)
    np.testing.assert_allclose(sp.factors, truth, atol=1e-4)
    assert sp.measured.all() and np.all(sp.sigma < 1e-4)
    assert sp.significant
    assert sp.jitter == pytest.approx(_robust_spread(truth), rel=0.05)


def test_the_charts_events_are_read_at_their_sweeps_speed(jittery):
    chart, true, events, info = jittery
    sp = C.chart_sweep_speeds(events, chart, true, t_start_us=0)
    plain = C.chart_data(events, chart, true, t_start_us=0, rows_per_label=None)
    moved = C.chart_data(events, chart, true, t_start_us=0, rows_per_label=None,
                         sweep_speeds=sp)  # fmt: skip
    assert np.array_equal(plain.pixel, moved.pixel)
    assert np.array_equal(plain.mask, moved.mask)
    cols = np.broadcast_to(plain.column[:, None], plain.t_us.shape)
    want = ev.reconstruction.warp_times(
        plain.t_us[plain.mask], cols[plain.mask], sp.offsets_us, sp.period_us, sp.factors
    )
    np.testing.assert_array_equal(moved.t_us[moved.mask], want)
    assert np.abs(moved.t_us - plain.t_us)[plain.mask].max() > 10.0  # (µs: moved)
    crop = sp.columns(4, 10)
    assert np.array_equal(crop.offsets_us, sp.offsets_us[4:10])
    assert np.array_equal(crop.factors, sp.factors)


def test_a_jittery_mirrors_chart_is_fitted_at_each_sweeps_speed(jittery, fits, tmp_path):
    chart, true, events, info = jittery
    each, one = fits
    # The file keeps what was measured: the spread as the rig's key, the factors.
    ev.calibration.save_calibration(tmp_path / "c.json", each)
    back = ev.load_calibration(tmp_path / "c.json")
    assert back.rig.effects.sweep_rate_jitter == pytest.approx(
        float(each.rig.effects.sweep_rate_jitter)
    )
    assert len(back.report["chart_sweep_speeds"]) == 8
    assert each.sweep_speeds_used and not one.sweep_speeds_used
    truth = info.speed_factor / info.speed_factor.mean()
    np.testing.assert_allclose(each.sweep_speeds.factors, truth, atol=3e-4)
    report = each.calibration.report
    assert report["sweep_speed"].startswith("each of 8 sweeps read at its own speed")
    assert report["sweep_rate_jitter"] == pytest.approx(_robust_spread(truth), rel=0.1)
    assert one.calibration.report["sweep_speed"] == "not measured (one speed)"
    assert one.rig.effects.sweep_rate_jitter == 0.0
    # One speed for all sweeps: the misfit reads as sensor noise that is not there.
    assert each.rig.effects.threshold_noise < 0.002
    assert one.rig.effects.threshold_noise > 2 * each.rig.effects.threshold_noise

    def map_error(res):
        return float(np.sqrt(np.mean((res.threshold_on_map - info.threshold_on) ** 2)))

    assert map_error(each) < 0.7 * map_error(one)


def test_the_charts_sweep_speeds_help_a_held_out_scene(jittery, fits):
    chart, true, _, _ = jittery
    scene = ev.load_scene("colorchecker", (chart.height, chart.width))
    events = ev.simulate(scene, true, sweeps=1, key=jr.key(3))
    truth = scene.truth_cube(true.grid)
    sam = [ev.evaluate(ev.reconstruct(events, r.calibration), truth)["sam_deg"]
           for r in fits]  # fmt: skip
    assert sam[0] < sam[1] - 0.3, sam


def test_a_steady_mirrors_chart_keeps_one_speed():
    """Per-crossing noise scatters the factors; they stay within their errors."""
    chart = ev.load_scene("gray-chart", (12, 16))
    events = ev.simulate(chart, ev.Rig(threshold_noise=0.02), sweeps=6, key=jr.key(5))
    res = ev.calibrate(events, chart, ev.Rig())
    sp = res.sweep_speeds
    assert sp is not None and sp.measured.sum() >= 5
    assert not sp.significant and not res.sweep_speeds_used
    assert np.all(np.abs(sp.factors - 1.0) < 4 * sp.sigma + 1e-4)
    assert res.rig.effects.sweep_rate_jitter == 0.0
    assert res.calibration.report["sweep_speed"].startswith("one speed (6 sweeps agree")


def test_too_few_sweeps_are_not_measured():
    chart = ev.load_scene("gray-chart", (12, 8))
    events = ev.simulate(chart, ev.Rig(sweep_rate_jitter=0.003), sweeps=2, key=jr.key(1))
    assert C.chart_sweep_speeds(events, chart, ev.Rig(), t_start_us=0) is None


def test_a_failed_fit_at_the_sweeps_speeds_falls_back_to_one(monkeypatch):
    """Should the fit at the sweeps' own speeds fail, the chart is fitted at one speed
    as before and the report says why."""
    from evhsi_jax._calibrate import _fit

    chart = ev.load_scene("gray-chart", (12, 16))
    events = ev.simulate(chart, ev.Rig(sweep_rate_jitter=0.003), sweeps=6, key=jr.key(2))
    once = _fit._fit_chart_once
    tried = []

    def failing(*a, **kw):
        tried.append(kw.get("sweep_speeds", "measure"))
        if isinstance(kw.get("sweep_speeds"), C.ChartSpeeds):
            raise _fit.NotConverged("(a stand-in for a fit that fails)")
        return once(*a, **kw)

    monkeypatch.setattr(_fit, "_fit_chart_once", failing)
    res = ev.calibrate(events, chart, ev.Rig())
    assert [type(t) for t in tried] == [str, C.ChartSpeeds, type(None)]
    assert res.sweep_speeds is tried[1] and not res.sweep_speeds_used
    assert res.rig.effects.sweep_rate_jitter == 0.0
    assert res.calibration.report["sweep_speed"].startswith("one speed: the fit at the 6")
