"""Dynamic scenes: per-sweep scenes for the simulator, their motion and truth."""

import math

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._model._dynamic import (
    changed_pixels,
    dynamic_scene,
    iridescent_reflectance,
    moving_chart,
    truth_cubes,
)


@pytest.mark.parametrize("name", ["translate", "rotate", "iridescent", "mixed"])
def test_presets_share_size_and_palette(name):
    scenes = dynamic_scene(name, (12, 16), sweeps=5)
    assert len(scenes) == 5
    assert {(s.height, s.width) for s in scenes} == {(12, 16)}
    assert len({s.palette.shape for s in scenes}) == 1  # one compilation for all
    assert all(s.wavelengths_nm is scenes[0].wavelengths_nm for s in scenes)


def test_translation_moves_the_chart_by_the_velocity():
    scenes = moving_chart((10, 30), 5, velocity_px_per_sweep=1.0, chart_height=6)
    bg = scenes[0].palette.shape[0] - 1
    # Column of the chart's left edge in its middle row, per sweep: +1 px per sweep.
    left = [int(np.argmax(s.labels[5] != bg)) for s in scenes]
    assert np.array_equal(np.diff(left), [1, 1, 1, 1])
    # The pixels the chart covers keep their patch pattern, shifted.
    a, b = scenes[0].labels[:, :20], scenes[2].labels[:, 2:22]
    assert np.array_equal(a, b)


def test_translation_turns_back_at_the_edge():
    scenes = moving_chart((10, 20), 40, velocity_px_per_sweep=1.0, chart_height=6)
    bg = scenes[0].palette.shape[0] - 1
    left = np.array([int(np.argmax(s.labels[5] != bg)) for s in scenes])
    assert left.min() == 0 and left.max() == 20 - 9  # chart 6x9 stays in frame
    assert np.any(np.diff(left) < 0) and np.any(np.diff(left) > 0)


def test_rotation_by_180_degrees_flips_the_chart():
    scenes = moving_chart(
        (8, 12), 2, velocity_px_per_sweep=0.0, deg_per_sweep=180.0, chart_height=8
    )
    a, b = scenes[0].labels, scenes[1].labels
    assert np.array_equal(b, a[::-1, ::-1])


def test_iridescent_peak_follows_the_thin_film_law():
    wl = np.arange(380.0, 781.0, 1.0)
    for theta in (0.0, 30.0, 60.0):
        r = iridescent_reflectance(wl, theta, peak_nm=680.0, index=1.4)
        s = math.sin(math.radians(theta)) / 1.4
        assert wl[np.argmax(r)] == pytest.approx(680.0 * math.sqrt(1 - s * s), abs=1)
        assert 0.0 <= r.min() and r.max() <= 1.0
    scenes = dynamic_scene("iridescent", (12, 16), sweeps=31, rock_sweeps=60)
    peaks = [s.wavelengths_nm[np.argmax(s.palette[-1])] for s in scenes]
    assert peaks[0] == pytest.approx(680.0, abs=5)
    assert np.all(np.diff(peaks) <= 0) and peaks[-1] < 560.0  # blue shift to 60°


def test_changed_pixels_and_truth():
    rig = ev.Rig()
    scenes = dynamic_scene("translate", (8, 24), sweeps=3, velocity_px_per_sweep=1.0)
    truth = truth_cubes(scenes, rig.grid)
    assert truth.shape == (3, 8, 24, rig.channels) and truth.dtype == np.float32
    ch = changed_pixels(scenes, rig.grid)
    assert not ch[0].any() and ch[1].any()
    expect = np.any(np.abs(truth[2] - truth[1]) > 1e-6, axis=-1)
    assert np.array_equal(ch[2], expect)


def test_simulate_takes_per_sweep_scenes():
    rig = ev.Rig()
    scenes = dynamic_scene("mixed", (6, 10), sweeps=2)
    events = ev.simulate(scenes, rig, sweeps=2, key=jr.key(0))
    sw = ev.io.split_sweeps(events, period_us=float(rig.period_us))
    assert len(sw) == 2 and all(len(s) > 0 for s in sw)
    static = ev.simulate(scenes[0], rig, sweeps=1, key=jr.key(0))
    # The first sweep sees the first scene only: identical events.
    assert np.array_equal(sw[0].t_us, static.t_us)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(name="spin"), "unknown dynamic scene"),
        (dict(name="translate", sweeps=0), "sweeps must be"),
        (dict(name="translate", size=(2, 3)), "at least 4x4"),
        (dict(name="translate", background="pink"), "background"),
    ],
)
def test_bad_arguments(kw, match):
    name = kw.pop("name")
    with pytest.raises(ValueError, match=match):
        dynamic_scene(name, **kw)
