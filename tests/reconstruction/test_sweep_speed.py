"""Each sweep's mirror speed, measured from the recording (`_sweep_speed`,
`reconstruct(sweep_speed=...)`, `evhsi reconstruct --sweep-speed`)."""

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._base._numba import numba_available
from evhsi_jax._reconstruct import _sweep_speed, warp_times
from evhsi_jax.cli import main

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not available")

SIZE = (16, 24)
#: Mirror-speed jitter and threshold noise of the sensor: with key 16 its two sweeps
#: run 0.30 % slower and 0.21 % faster than the calibration's.
SENSOR = {"sweep_rate_jitter": 0.003, "threshold_noise": 0.005}


@pytest.fixture(scope="module")
def jittery():
    """Two sweeps of `tcs` from a sensor whose mirror speed varies per sweep; the
    reconstruction's rig is the sensor's (its noise keys give the noise model)."""
    rig = ev.Rig.from_dict(SENSOR)
    scene = ev.load_scene("tcs", SIZE)
    events, info = ev.simulate(scene, rig, sweeps=2, key=jr.key(16), return_info=True)
    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    return cal, scene, events, info


def test_warp_times_moves_the_band_to_the_nominal_sweep():
    """Local time t of a sweep with factor f goes to f (t + τ) − τ, within the sweep;
    factor 1 changes nothing; the order of a pixel's events is kept."""
    period = 1000.0
    offsets = np.array([0.0, -120.0])
    t = np.array([10.0, 400.0, 990.0, 1010.0, 1500.0, 1999.0])
    col = np.array([0, 1, 1, 0, 1, 0])
    f = np.array([1.01, 0.99])
    got = warp_times(t, col, offsets, period, f)
    local, sweep = t % period, np.floor(t / period)
    tau = offsets[col]
    want = sweep * period + np.clip(f[sweep.astype(int)] * (local + tau) - tau, 0,
                                    np.nextafter(period, 0))  # fmt: skip
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert got[1] == pytest.approx(1.01 * (400.0 - 120.0) + 120.0)
    np.testing.assert_array_equal(np.floor(got / period), sweep)  # in its sweep
    np.testing.assert_array_equal(warp_times(t, col, offsets, period, [1.0, 1.0]), t)
    dense = np.sort(np.random.default_rng(0).uniform(0, 2 * period, 500))
    moved = warp_times(dense, np.zeros(500, int), offsets, period, f)
    assert np.all(np.diff(moved) >= 0)


def test_warp_lists_numba_is_numpy():
    """The pixel lists' one-pass numba warp gives NumPy's values to the bit."""
    from evhsi_jax._base._numba import use_backend

    rng = np.random.default_rng(1)
    w, period = 7, 1000.0
    counts = rng.integers(0, 9, 5 * w)
    starts = np.cumsum(counts) - counts
    t = np.concatenate([np.sort(rng.uniform(0, 2 * period, c)) for c in counts])
    lists = (counts, starts, t, np.ones(t.size, np.int8))
    offsets = -np.linspace(0.0, 150.0, w)
    got = _sweep_speed.warp_lists(lists, w, offsets, period, [1.01, 0.995])[2]
    with use_backend("numpy"):
        want = _sweep_speed.warp_lists(lists, w, offsets, period, [1.01, 0.995])[2]
    np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got, t)
    assert _sweep_speed.warp_lists(lists, w, offsets, period, [1.0, 1.0]) is lists


def _sweep(events, info, cal, s):
    """Sweep `s` of the recording, as a recording of its own."""
    period = float(cal.rig.period_us)
    return events.time_window(int(round(s * period)), int(round((s + 1) * period)))


def test_the_factor_is_measured_and_helps(jittery):
    """From one sweep the estimate lies within 0.001 of its true factor, and the cube
    is closer to the truth than with the calibration's speed (and as close as with
    the true factor); in the recording of both sweeps each sweep's factor is
    measured (with the sweep before it, :func:`_sweep_speed._sweep_subset`) and
    helps too."""
    cal, scene, events, info = jittery
    truth = scene.truth_cube(cal.rig.grid)
    true = np.asarray(info.speed_factor)
    assert np.all(np.abs(true - 1) > 0.002)  # (the draws this test is about)
    one = _sweep(events, info, cal, 0)
    cubes, infos = {}, {}
    for mode in ("auto", "off", [true[0]]):
        key = mode if isinstance(mode, str) else "true"
        cubes[key], infos[key] = ev.reconstruct(one, cal, sweep_speed=mode,
                                                return_info=True)  # fmt: skip
    assert abs(infos["auto"].sweep_speed[0] - true[0]) < 1e-3
    assert infos["off"].sweep_speed is None
    np.testing.assert_array_equal(infos["true"].sweep_speed, true[:1])
    sam = {k: ev.evaluate(c, truth)["sam_deg"] for k, c in cubes.items()}
    assert sam["auto"] < sam["off"] - 0.1, sam
    assert sam["auto"] < sam["true"] + 0.2, sam
    cube, both = ev.reconstruct(events, cal, return_info=True)
    np.testing.assert_allclose(both.sweep_speed, true, atol=1e-3)
    steady = ev.reconstruct(events, cal, sweep_speed="off")
    both_sam = ev.evaluate(cube, truth)["sam_deg"]
    assert both_sam < ev.evaluate(steady, truth)["sam_deg"] - 0.1
    _, given = ev.reconstruct(events, cal, sweep_speed=true, return_info=True)
    np.testing.assert_array_equal(given.sweep_speed, true)


def test_a_steady_mirror_shares_one_factor(jittery):
    """A rig whose `sweep_rate_jitter` is 0 (what `calibrate` writes when the chart's
    sweeps keep one speed) gives the sweeps of a recording one factor: the mean of
    their own estimates, shrunk as those are."""
    cal, _, events, _ = jittery
    _, own = ev.reconstruct(events, cal, return_info=True)
    steady = ev.Calibration(cal.rig.replace_host(sweep_rate_jitter=0.0),
                            cal.threshold_on, cal.threshold_off)  # fmt: skip
    _, one = ev.reconstruct(events, steady, return_info=True)
    assert one.sweep_speed[0] == one.sweep_speed[1]
    assert abs(own.sweep_speed[0] - own.sweep_speed[1]) > 0.003  # (apart, as drawn)
    # (the shrinkage moves the mean only: the sweeps' own factors keep its result)
    assert one.sweep_speed[0] == pytest.approx(own.sweep_speed.mean(), abs=1e-12)


def test_both_backends_use_the_same_estimate(jittery):
    cal, _, events, info = jittery
    one = _sweep(events, info, cal, 1)
    _, fused = ev.reconstruct(one, cal, backend="fused", return_info=True)
    _, jx = ev.reconstruct(one, cal, backend="jax", return_info=True)
    assert fused.sweep_speed[0] != 1.0
    np.testing.assert_array_equal(fused.sweep_speed, jx.sweep_speed)


def test_the_common_level_is_shrunk():
    """A recording's common deviation is shrunk by the estimate's bias (none left
    below it); the sweeps' differences are kept."""
    b = _sweep_speed.SPEED_BIAS
    ok = np.array([True, True, True])
    got = _sweep_speed.shrink_common([1 + 0.5 * b, 1 + 0.7 * b, 1 + 0.3 * b], ok)
    np.testing.assert_allclose(got - 1, [0.0, 0.2 * b, -0.2 * b], atol=1e-15)
    got = _sweep_speed.shrink_common([1.004], np.array([True]))
    assert got[0] - 1 == pytest.approx(0.004 - b**2 / 0.004)
    got = _sweep_speed.shrink_common([1.004, 1.0], np.array([True, False]))
    assert got[1] == 1.0  # (a sweep not measured stays)


def test_an_ideal_sensor_keeps_its_speed():
    """Without mirror jitter the estimate stays near 1 (a noise model of
    `IDEAL_NOISE` weights the rows of a sensor that has none) and the cube hardly
    moves."""
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", SIZE)
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(4), return_info=True)
    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    auto, inf = ev.reconstruct(events, cal, return_info=True)
    off = ev.reconstruct(events, cal, sweep_speed="off")
    assert abs(inf.sweep_speed[0] - 1) < 1e-3
    assert ev.metrics.sam_map_deg(auto, off).mean() < 0.1


def test_the_search_gives_up_at_its_bound():
    """A misfit that keeps falling has no minimum to measure: the factor stays 1."""
    f, n = _sweep_speed._minimise(lambda f: -f)
    assert f == 1.0 and n > 3
    f, _ = _sweep_speed._minimise(lambda f: (f - 1.0031) ** 2)
    assert f == pytest.approx(1.0031, abs=1e-9)  # (a parabola's own vertex)


def test_per_sweep_runs_measure_each_sweep(jittery, tmp_path):
    """`reconstruct_sweeps` measures each sweep's factor (its index entry) and
    carries the references at the moved times; a moving scene keeps factors near 1
    (its sweeps' first rows refer to another spectrum: left out of the estimate)."""
    cal, scene, events, info = jittery
    res = ev.reconstruct_sweeps(events, cal, tmp_path / "a", preview=False)
    got = [e["sweep_speed"] for e in res.index["sweeps"]]
    np.testing.assert_allclose(got, info.speed_factor, atol=1.5e-3)
    off = ev.reconstruct_sweeps(events, cal, tmp_path / "b", preview=False,
                                sweep_speed="off")  # fmt: skip
    assert all("sweep_speed" not in e for e in off.index["sweeps"])
    truth = scene.truth_cube(cal.rig.grid)
    sams = [
        [ev.evaluate(c["cube"], truth)["sam_deg"] for _, c in
         ev.video.iter_sweep_cubes(tmp_path / d)]
        for d in ("a", "b")
    ]  # fmt: skip
    assert np.mean(sams[0]) < np.mean(sams[1]) - 0.3, sams
    rig = ev.Rig()
    scenes = ev.forward.dynamic_scene("translate", (12, 20), sweeps=3,
                                      velocity_px_per_sweep=1.0)  # fmt: skip
    moving, minfo = ev.simulate(scenes, rig, sweeps=3, key=jr.key(3), return_info=True)
    mcal = ev.Calibration(rig, minfo.threshold_on, minfo.threshold_off)
    res = ev.reconstruct_sweeps(moving, mcal, tmp_path / "m", preview=False)
    assert all(abs(e["sweep_speed"] - 1) < 2e-3 for e in res.index["sweeps"])


def test_bad_factors_are_refused(jittery):
    cal, _, events, _ = jittery
    for bad, words in (
        ("fast", "sweep_speed must be 'auto', 'off' or one factor per sweep"),
        ([1.0], "has 1 factor(s); the recording uses 2 sweep(s)"),
        ([1.0, 1.2], "within 1 ± 0.03"),
        ([1.0, np.nan], "within 1 ± 0.03"),
    ):
        with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
            ev.reconstruct(events, cal, sweep_speed=bad)


def test_cli_sweep_speed(jittery, tmp_path, capsys):
    """`--sweep-speed` is the API's `sweep_speed` (auto by default; the summary
    lists the factors used); a bad value is one line and exit 2."""
    cal, _, events, _ = jittery
    events.save_npz(tmp_path / "ev.npz")
    cal.save(tmp_path / "cal.json")
    cal = ev.load_calibration(tmp_path / "cal.json")
    base = ["reconstruct", str(tmp_path / "ev.npz"), "--calib", str(tmp_path / "cal.json"),
            "--quiet"]  # fmt: skip
    for opt, mode in ((None, "auto"), ("off", "off"), ("1.004,0.997", [1.004, 0.997])):
        dest = tmp_path / f"c{opt}.npz"
        capsys.readouterr()
        assert main(base + ["--out", str(dest)]
                    + ([] if opt is None else ["--sweep-speed", opt])) == 0  # fmt: skip
        ref, inf = ev.reconstruct(events, cal, sweep_speed=mode, return_info=True)
        np.testing.assert_array_equal(np.load(dest)["cube"], ref)
        printed = capsys.readouterr().out
        # (said when measured or given, not with off)
        assert ("mirror speed per sweep" in printed) == (inf.sweep_speed is not None)
        if opt is not None and opt != "off":
            assert "+0.40, -0.30 %" in printed
    # Per sweep: each sweep measured, the summary gives their range.
    capsys.readouterr()
    assert main(base + ["--out", str(tmp_path / "frames"), "--per-sweep"]) == 0
    printed = capsys.readouterr().out
    got = [e["sweep_speed"] for e in ev.video.load_sweep_index(tmp_path / "frames")["sweeps"]]
    lo, hi = 100 * (min(got) - 1), 100 * (max(got) - 1)
    assert f"mirror speed per sweep {lo:+.2f} to {hi:+.2f} %" in printed, printed
    assert lo < -0.1 and hi > 0.1  # (this recording's sweeps: -0.30 % and +0.21 %)
    for bad, words in (("quick", "--sweep-speed must be auto, off or factors"),
                       ("1.0", "has 1 factor(s)"),
                       ("1.0,1.0", "with --per-sweep, --sweep-speed is auto or off")):  # fmt: skip
        extra = ["--per-sweep"] if "per-sweep" in words else []
        code = main(base + ["--out", str(tmp_path / "bad.npz"), "--sweep-speed", bad]
                    + extra)  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert words in err
        assert not (tmp_path / "bad.npz").exists()
