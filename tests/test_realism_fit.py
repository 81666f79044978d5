"""Real sensors, the calibration's fit: it measures the noise it was given and fits
the sweep's curvature (also under a known photoreceptor low-pass: `-m slow`)."""

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev


def test_calibration_measures_noise_and_hot_pixels():
    chart = ev.load_scene("gray-chart", (24, 48))
    true = ev.Rig(threshold_noise=0.01, hot_pixel_fraction=0.004, noise_rate_hz=2.0)
    events, info = ev.simulate(chart, true, sweeps=2, key=jr.key(4), return_info=True)
    res = ev.calibrate(events, chart, ev.Rig())
    assert abs(res.rig.effects.threshold_noise / 0.01 - 1.0) < 0.2
    assert np.array_equal(res.hot_pixels, info.hot_pixels)
    assert 1.0 < res.rig.noise_rate_hz < 3.0
    assert res.converged


def test_calibration_fits_curvature():
    chart = ev.load_scene("gray-chart", (24, 32))
    events = ev.simulate(chart, ev.Rig(sweep_curvature_nm=3.0), sweeps=2, key=jr.key(6))
    res = ev.calibrate(events, chart, ev.Rig())
    assert abs(float(res.rig.sweep_curvature_nm) - 3.0) < 0.5
    assert res.rig.effects.threshold_noise < 0.002  # no noise where there was none


@pytest.mark.slow  # ~1-2 min: the low-passed chart traces cost most of the fit
def test_calibration_fits_curvature_and_a_known_lowpass():
    chart = ev.load_scene("gray-chart", (24, 32))
    true = ev.Rig(sweep_curvature_nm=3.0, photoreceptor_hz=10000.0)
    events = ev.simulate(chart, true, sweeps=2, key=jr.key(6))
    res = ev.calibrate(events, chart, ev.Rig(photoreceptor_hz=10000.0))
    assert abs(float(res.rig.sweep_curvature_nm) - 3.0) < 0.5
    assert res.rms_residual < 0.01  # the low-passed chart is explained exactly
    assert res.rig.effects.threshold_noise < 0.002
