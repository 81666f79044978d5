"""Real sensors, calibration side: the calibration measures the noise it was given,
fits the sweep's curvature under a known low-pass, refuses what it cannot fit, and the
CLI and Python reconstruct the same cube from its file (split from test_realism.py so
the two halves run in parallel)."""

import json

import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax.cli import main


@pytest.fixture(scope="module")
def realistic_files(tmp_path_factory):
    """The CLI in-process (`main`: the same code as the `evhsi` program, without a
    fresh compilation per subprocess)."""
    d = tmp_path_factory.mktemp("real")
    (d / "rig.json").write_text(json.dumps({"sensor": "realistic"}))
    for scene, name, sweeps in (("gray-chart", "gray", 2), ("colorchecker", "cc", 1)):
        assert main(["simulate", "--scene", scene, "--size", "16x32", "--sweeps",
                     str(sweeps), "--rig", str(d / "rig.json"), "--seed", "3",
                     "--quiet", "--out", str(d / f"{name}.npz"), "--truth",
                     str(d / f"{name}_t.npz")]) == 0  # fmt: skip
    # (no photoreceptor cut-off in --init: the calibration measures it)
    (d / "init.json").write_text(json.dumps({"threshold_on": 0.15}))
    assert main(["calibrate", str(d / "gray.npz"), "--init", str(d / "init.json"),
                 "--out", str(d / "cal.json")]) == 0  # fmt: skip
    assert main(["reconstruct", str(d / "cc.npz"), "--calib", str(d / "cal.json"),
                 "--out", str(d / "cube.npz"), "--quiet"]) == 0  # fmt: skip
    return d


def test_python_and_cli_reconstruct_the_same_cube(realistic_files):
    d = realistic_files
    cal = ev.load_calibration(d / "cal.json")
    assert cal.threshold_on is not None and cal.hot_pixels is not None
    assert cal.rig.effects.threshold_noise > 0
    assert cal.report["psf_sigma_px"] in (0.4, 0.5, 0.6)  # the preset's lens: 0.5 px
    assert float(cal.rig.effects.psf_sigma_px) == cal.report["psf_sigma_px"]  # in the rig
    # The preset's 10 kHz photoreceptor, measured although --init had none (the
    # preset's other effects, the skewed band above all, bias it on a chart this
    # small: 40x64, 8 sweeps gave 7.5 kHz).
    assert 4000.0 < cal.rig.effects.photoreceptor_hz < 20000.0
    assert cal.report["photoreceptor"].startswith("fitted")
    cube = ev.reconstruct(ev.read_events(d / "cc.npz"), cal)
    np.testing.assert_array_equal(cube, np.load(d / "cube.npz")["cube"])
    assert cube.min() >= 0.0 and cube.max() <= 1.5
    with pytest.raises(ValueError, match="load_calibration"):
        ev.reconstruct(ev.read_events(d / "cc.npz"), ev.Rig.load(d / "cal.json"))


def test_calibrating_a_scene_that_is_not_the_chart_fails(realistic_files):
    """A ColorChecker capture calibrated as a gray chart: the fit cannot explain it
    and says so (a ValueError: the CLI's one line and exit 2, see test_reliability)
    instead of returning a rig. A short step budget keeps the test cheap; the full
    budget ends the same way (README, Real sensors)."""
    d = realistic_files
    events = ev.read_events(d / "cc.npz")
    chart = ev.load_scene("gray-chart", (events.height, events.width))
    with pytest.raises(ValueError, match="does not fit its data"):
        ev.calibrate(events, chart, ev.Rig(), max_steps=12)


def test_photoreceptor_passes_option(realistic_files, tmp_path, capsys):
    """`reconstruct --photoreceptor-passes N` solves with N Gauss–Newton passes of the
    photoreceptor model (the Python API's `ProblemConfig(lowpass_passes=N)`, the
    same cube); a value out of range is one line and exit 2, before any work."""
    from evhsi_jax.reconstruction import ProblemConfig

    d = realistic_files
    events = ev.read_events(d / "cc.npz")
    cal = ev.load_calibration(d / "rig.json")  # the preset: a 10 kHz photoreceptor
    cubes = []
    for n in (0, 2):
        out = tmp_path / f"c{n}.npz"
        assert main(["reconstruct", str(d / "cc.npz"), "--calib", str(d / "rig.json"),
                     "--out", str(out), "--photoreceptor-passes", str(n),
                     "--quiet"]) == 0  # fmt: skip
        cube = np.load(out)["cube"]
        ref = ev.reconstruct(events, cal, config=ProblemConfig(lowpass_passes=n))
        np.testing.assert_array_equal(cube, ref)
        cubes.append(cube)
    assert not np.array_equal(cubes[0], cubes[1])  # the passes ran
    capsys.readouterr()
    code = main(["reconstruct", str(d / "cc.npz"), "--calib", str(d / "rig.json"),
                 "--out", str(tmp_path / "bad.npz"), "--photoreceptor-passes", "-1"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "--photoreceptor-passes must be in [0, 16]" in err
    assert not (tmp_path / "bad.npz").exists()
