"""Stray (background) events inside a pixel's lit interval: found by the fit of the
fused kernel's answer and removed (`_pipeline.repair_strays`)."""

from collections import Counter

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._base._numba import numba_available
from evhsi_jax._reconstruct import ProblemConfig, _fused, _pipeline
from evhsi_jax._reconstruct._pixels import pixel_lists

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not available")

SIZE = (12, 16)


def _pixel_events(events, w):
    x, y, t, p = (np.asarray(a) for a in (events.x, events.y, events.t_us, events.p))
    return list(zip((y.astype(np.int64) * w + x).tolist(), t.tolist(), p.tolist()))


@pytest.fixture(scope="module")
def background():
    """One sweep of the ColorChecker from an otherwise ideal sensor with background
    activity of 20 Hz per pixel (a stray event in the lit interval of ~40 % of the
    pixels), and the same capture without it (same key: the same signal events)."""
    scene = ev.load_scene("colorchecker", SIZE)
    out = {}
    for rate in (0.0, 20.0):
        rig = ev.Rig(noise_rate_hz=rate)
        out[rate] = (rig, *ev.simulate(scene, rig, sweeps=1, key=jr.key(3),
                                       return_info=True))  # fmt: skip
    truth = np.asarray(scene.truth_cube(out[0.0][0].grid), np.float64)
    return out, truth


def test_stray_events_are_found_and_removed(background):
    """Only pixels with a background event change, and on those with one inside the
    lit interval the error falls by more than half; without background activity in
    the calibration nothing is searched."""
    out, truth = background
    h, w = SIZE
    rig, events, info = out[20.0]
    _, clean, _ = out[0.0]
    left = Counter(_pixel_events(clean, w))
    noise = []
    for e in _pixel_events(events, w):
        if left[e] > 0:
            left[e] -= 1
        else:
            noise.append(e)
    first, last = {}, {}
    for i, t, _ in sorted(_pixel_events(clean, w)):
        first.setdefault(i, t)
        last[i] = t
    touched = np.zeros(h * w, bool)  # any background event
    inside = np.zeros(h * w, bool)  # one inside the pixel's lit interval
    for i, t, _ in noise:
        touched[i] = True
        inside[i] |= i in first and first[i] <= t <= last[i]
    assert inside.sum() >= 20

    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    on, info_on = ev.reconstruct(events, cal, return_info=True, backend="fused")
    off = ev.reconstruct(
        events, cal, config=ProblemConfig(stray_z=0.0), backend="fused"
    )
    changed = np.any(on != off, axis=-1).ravel()
    # (a repaired answer may clip to the same cube; a pixel may lose two strays)
    assert info_on.stray_events >= changed.sum() >= 0.5 * info_on.stray_events > 0
    assert not np.any(changed & ~touched)  # pixels without one keep their answer
    sam_on = ev.metrics.sam_map_deg(on, truth).ravel()
    sam_off = ev.metrics.sam_map_deg(off, truth).ravel()
    assert sam_off[inside].mean() > 10.0  # what a stray event does unrepaired
    assert sam_on[inside].mean() < 0.5 * sam_off[inside].mean()

    quiet = ev.Calibration(
        rig.replace_host(noise_rate_hz=0.0, threshold_noise=0.01),
        info.threshold_on,
        info.threshold_off,
    )
    _, info_q = ev.reconstruct(events, quiet, return_info=True, backend="fused")
    assert info_q.stray_events == 0


def test_two_strays_in_two_sweeps_are_both_removed():
    """Two stray events of the wrong polarity put into one pixel's lit intervals, one
    per sweep, of a two-sweep capture without background (each pixel of a sample in
    its own run): the second round finds the second one in about half of them, and
    those get back the answer they had without the strays; the others keep theirs."""
    h, w = SIZE
    scene = ev.load_scene("colorchecker", SIZE)
    clean, info = ev.simulate(scene, ev.Rig(), sweeps=2, key=jr.key(3),
                              return_info=True)  # fmt: skip
    # A calibration that measured background activity (the search is on).
    cal = ev.Calibration(ev.Rig(noise_rate_hz=20.0), info.threshold_on,
                         info.threshold_off)  # fmt: skip
    ref = ev.reconstruct(clean, cal, backend="fused", sweep_speed="off")
    ref = ref.reshape(h * w, -1)  # (the speed estimate off: the events differ)
    x, y, t, pol = (np.asarray(a) for a in (clean.x, clean.y, clean.t_us, clean.p))
    flat = y.astype(np.int64) * w + x
    repaired = 0
    for p in range(0, h * w, 12):
        mine = np.flatnonzero(flat == p)
        add = [mine[j : j + 2] for j in (5, mine.size // 2 + 8)]
        add_t = [(t[i] + t[i2]) // 2 for i, i2 in add]  # mid-gap, against the next
        add_p = [1 - pol[i2] for _, i2 in add]
        order = np.argsort(np.concatenate([t, add_t]), kind="stable")
        both = ev.EventStream(
            x=np.concatenate([x, [p % w] * 2])[order],
            y=np.concatenate([y, [p // w] * 2])[order],
            p=np.concatenate([pol, add_p])[order],
            t_us=np.concatenate([t, add_t])[order],
            width=w, height=h, trigger_t_us=clean.trigger_t_us,
            trigger_p=clean.trigger_p, trigger_id=clean.trigger_id,
        )  # fmt: skip
        on, got = ev.reconstruct(both, cal, return_info=True, backend="fused",
                                 sweep_speed="off")  # fmt: skip
        sam = float(ev.metrics.sam_map_deg(on.reshape(h * w, -1)[p][None],
                                           ref[p][None])[0])  # fmt: skip
        assert got.stray_events in (0, 2)
        if got.stray_events == 2:
            repaired += 1
            assert sam < 0.05
    assert repaired >= 6  # of 16


def test_undropped():
    """Variant slots back to the pixel's own event indices, any number of drops."""
    idx = np.array([0, 1, 2, 3, 0, 1, 2])
    drops = np.array([[1, -1]] * 4 + [[3, 0]] * 3)
    np.testing.assert_array_equal(
        _pipeline._undropped(idx, drops), [0, 2, 3, 4, 1, 2, 4]
    )


# ~100 s on a cold cache (its float32 JAX programs compile for ~70 s), 25 s warm. The
# JAX path's search also runs in every `make test` as the float64 reference of
# test_fused.py::test_noise_aware_fused_equals_float64_jax (stray events found there,
# cubes within 0.05° of the fused kernel's), so this float32 check is a slow one.
@pytest.mark.slow
def test_the_jax_backend_finds_the_same_strays(background):
    """The JAX path (`_chunk_fit`, `_solve_variants_jax`) flags and repairs the same
    pixels as the fused kernel, to the same answers within float32 rounding."""
    out, _ = background
    rig, events, info = out[20.0]
    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    fused, f_info = ev.reconstruct(events, cal, return_info=True, backend="fused")
    jx, j_info = ev.reconstruct(events, cal, return_info=True, backend="jax")
    off = ev.reconstruct(events, cal, config=ProblemConfig(stray_z=0.0), backend="jax")
    assert j_info.stray_events > 0.9 * f_info.stray_events
    assert np.mean(ev.metrics.sam_map_deg(jx, fused) < 0.5) > 0.97
    changed = np.any(jx != off, axis=-1)
    assert changed.sum() >= 0.9 * j_info.stray_events


def test_kernel_fit_is_the_rows_misfit(background):
    """The kernel's per-pixel fit: NaN without a noise model; with one, the largest
    |residual| (σ), its event's index within the pixel and the capped sum of squares,
    consistent with each other."""
    out, _ = background
    h, w = SIZE
    rig, events, info = out[20.0]
    t0 = int(events.trigger_t_us[0])
    fits = {}
    for noise in (None, _pipeline.noise_model(rig)):
        screened, _, _ = _pipeline.screen_events(events, rig, t0, noise, 1)
        counts, starts, t, s = pixel_lists(screened, t0)
        prob = _fused.FusedProblem(
            rig, _pipeline.channel_table(rig), ProblemConfig(),
            _pipeline.solver_spec("auto"), w, np.asarray(rig.column_offsets(w)), 1,
            noise,
        )  # fmt: skip
        sel = np.flatnonzero(counts)
        fit = np.empty((sel.size, 3))
        _fused.solve_fused(
            prob, sel, starts, counts, t, s, np.zeros(h * w),
            info.threshold_on.reshape(-1), info.threshold_off.reshape(-1), fit=fit,
        )  # fmt: skip
        fits[noise is None] = (fit, counts[sel])
    assert np.all(np.isnan(fits[True][0]))
    fit, k = fits[False]
    z, i, total = fit.T
    assert np.all(np.isfinite(fit)) and np.all(z >= 0)
    assert np.all((i >= 0) & (i < k) & (i == np.round(i)))
    cap = ProblemConfig().robust_reject ** 2
    assert np.all(total >= np.minimum(z * z, cap) * (1 - 1e-12))
    assert np.all(total <= k * np.minimum(z * z, cap) * (1 + 1e-12))
    assert np.any(z > ProblemConfig().stray_z)  # the strays are seen


def test_sweep_span():
    """Each event's sweep: the first and last index of its sweep's events."""
    period = 100.0
    t = np.array([5.0, 50.0, 120.0, 130.0, 199.0, 350.0, 10.0, 260.0, 270.0])
    start = np.array([0, 6])  # two pixels: t[0:6] and t[6:9]
    k = np.array([6, 3])
    lo, hi = _pipeline._sweep_span(t, start, k, np.array([3, 1]), period)
    np.testing.assert_array_equal(lo, [2, 1])
    np.testing.assert_array_equal(hi, [4, 2])
    lo, hi = _pipeline._sweep_span(t, start, k, np.array([5, 0]), period)
    np.testing.assert_array_equal(lo, [5, 0])
    np.testing.assert_array_equal(hi, [5, 0])


def test_stray_z_option(background, tmp_path, capsys):
    """`reconstruct --stray-z Z` is `ProblemConfig(stray_z=Z)` (0: no search), and
    says how many stray events it removed (with `--per-sweep`, the run's total); a
    negative Z is one line and exit 2."""
    from evhsi_jax.cli import main

    out, _ = background
    rig, events, info = out[20.0]
    events.save_npz(tmp_path / "ev.npz")
    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    cal.save(tmp_path / "cal.json")
    cal = ev.load_calibration(tmp_path / "cal.json")
    for z, said in ((None, True), (0.0, False)):
        dest = tmp_path / f"c{z}.npz"
        args = ["reconstruct", str(tmp_path / "ev.npz"), "--calib",
                str(tmp_path / "cal.json"), "--out", str(dest), "--quiet",
                "--backend", "fused"]  # fmt: skip
        capsys.readouterr()
        assert main(args + ([] if z is None else ["--stray-z", str(z)])) == 0
        cfg = ProblemConfig() if z is None else ProblemConfig(stray_z=z)
        ref = ev.reconstruct(events, cal, config=cfg, backend="fused")
        np.testing.assert_array_equal(np.load(dest)["cube"], ref)
        printed = capsys.readouterr().out
        assert ("stray event(s) inside lit intervals removed" in printed) == said
    capsys.readouterr()  # per sweep: the run's total
    assert main(["reconstruct", str(tmp_path / "ev.npz"), "--calib",
                 str(tmp_path / "cal.json"), "--out", str(tmp_path / "frames"),
                 "--per-sweep", "--quiet", "--backend", "fused"]) == 0  # fmt: skip
    assert "stray event(s) inside lit intervals removed" in capsys.readouterr().out
    code = main(["reconstruct", str(tmp_path / "ev.npz"), "--calib",
                 str(tmp_path / "cal.json"), "--out", str(tmp_path / "bad.npz"),
                 "--stray-z", "-1"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "--stray-z must be a finite number >= 0" in err
    assert not (tmp_path / "bad.npz").exists()
