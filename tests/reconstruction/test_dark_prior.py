"""The dark-channel prior (`_problem.dark_strength`): one-sweep solves only, and a
pixel's share of it from the threshold noise alone.

Until the twenty-fifth session (2026-11-29) every solve with a noise model got it,
whatever its number of sweeps, and timestamp jitter counted in each pixel's share; on
the training scene `tcs` that cost a recording of several sweeps, or one sweep of a
sensor with jitter, more than 1° SAM (README, Real sensors, "The dark-channel prior's
strength"; `experiments/dark_prior.py`).
"""

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._reconstruct._problem import dark_strength
from evhsi_jax.reconstruction import ProblemConfig

SIZE = (16, 24)
NO_PRIOR = ProblemConfig(alpha_dark=0.0)


def test_strength_rule():
    cfg = ProblemConfig()
    assert dark_strength(1, cfg) == cfg.alpha_dark > 0
    assert dark_strength(2, cfg) == 0.0
    assert dark_strength(4, ProblemConfig(dark_sweeps=4)) == cfg.alpha_dark
    with pytest.raises(ValueError, match="dark_sweeps"):
        ProblemConfig(dark_sweeps=-1)


def _cubes(keys, sweeps, configs):
    rig = ev.Rig.from_dict(keys)
    scene = ev.load_scene("tcs", SIZE)
    truth = np.asarray(scene.truth_cube(rig.grid), np.float64)
    events, info = ev.simulate(scene, rig, sweeps=sweeps, key=jr.key(1),
                               return_info=True)  # fmt: skip
    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    cubes = [ev.reconstruct(events, cal, sweep_speed="off", config=c) for c in configs]
    return cubes, [ev.evaluate(c, truth)["sam_deg"] for c in cubes]


def test_prior_only_for_threshold_noise_in_one_sweep():
    """`tcs` 16×24, true rig and thresholds. Jitter alone (5 µs, one sweep): no
    share, so the answer is the one without the prior, bit for bit (it was 4.6°
    against 2.8° now). Threshold noise 0.01 from two sweeps: no prior either, and
    with it (`dark_sweeps=2`, the old rule) > 1° worse (4.6° against 3.2°). From
    one sweep it is on and helps."""
    (new, none), _ = _cubes({"timestamp_jitter_us": 5.0}, 1, [ProblemConfig(), NO_PRIOR])
    np.testing.assert_array_equal(new, none)
    (new, none, old), sam = _cubes(
        {"threshold_noise": 0.01}, 2, [ProblemConfig(), NO_PRIOR, ProblemConfig(dark_sweeps=2)]
    )
    np.testing.assert_array_equal(new, none)
    assert sam[0] < sam[2] - 1.0, sam
    _, (new, none) = _cubes({"threshold_noise": 0.01}, 1, [ProblemConfig(), NO_PRIOR])
    assert new < none - 0.2, (new, none)
