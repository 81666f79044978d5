"""The reconstruction pipeline: accuracy, hard cases, bucketing, compilation, gradients."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._reconstruct import (
    PixelEvents,
    ProblemConfig,
    group_pixels,
    pixel_system,
)
from evhsi_jax._reconstruct._implicit import reconstruct_pixels
from evhsi_jax._reconstruct._pipeline import _solve_chunk

SIZE = (8, 12)


@pytest.fixture(scope="module")
def capture():
    rig = ev.Rig()  # paper rig: threshold mismatch 0.01, refractory 50 µs
    scene = ev.load_scene("colorchecker", SIZE)
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(7), return_info=True)
    return rig, scene, events, info


@pytest.fixture(scope="module")
def cube_known_thresholds(capture):
    rig, _, events, info = capture
    return ev.reconstruct(
        events,
        rig,
        threshold_on_map=info.threshold_on,
        threshold_off_map=info.threshold_off,
        return_info=True,
    )


def test_colorchecker_accuracy_with_per_pixel_thresholds(
    capture, cube_known_thresholds
):
    rig, scene, _, _ = capture
    cube, info = cube_known_thresholds
    m = ev.evaluate(cube, scene.truth_cube(rig.grid))
    assert m["sam_deg"] < 5.0
    assert m["psnr_db"] > 30.0
    assert cube.dtype == np.float32 and np.all(np.isfinite(cube)) and np.all(cube >= 0)
    assert np.nanmax(info.kkt) < 1e-4  # the QPs were solved, not approximated


def test_nominal_thresholds_shift_scale_not_shape(capture, cube_known_thresholds):
    rig, scene, events, _ = capture
    nominal = ev.reconstruct(events, rig)
    truth = scene.truth_cube(rig.grid)
    known = cube_known_thresholds[0]
    # Threshold mismatch mostly rescales each pixel's spectrum: SAM barely changes,
    # the RMS error grows.
    assert ev.metrics.sam_deg(nominal, truth) < ev.metrics.sam_deg(known, truth) + 2.0
    assert ev.metrics.rms(nominal, truth) > ev.metrics.rms(known, truth)


def test_event_rows_vanish_at_the_truth(capture):
    """With priors off, the augmented Gram's quadratic form at [truth; 1] is ~0: every
    event is an exact constraint of the model (up to µs rounding)."""
    with jax.enable_x64(True):
        rig0 = ev.Rig(threshold_sigma=0.0)
        scene = ev.load_scene("colorchecker", (4, 6))
        events = ev.simulate(scene, rig0, sweeps=2, key=jr.key(0))
        truth = (
            scene.truth_cube(rig0.grid).reshape(-1, rig0.channels).astype(np.float64)
        )
        table = ev.forward.band_table(rig0).channels(rig0.grid.sub)
        cfg = ProblemConfig(alpha_int=0.0, alpha_spec=0.0, ridge=0.0)
        batches, _, _ = group_pixels(events, t_start_us=0, chunk_pixels=64)
        offsets = np.asarray(rig0.column_offsets(events.width))
        system = eqx.filter_jit(pixel_system)  # one compilation, not op by op
        for b in batches:
            for i in np.nonzero(b.pixel >= 0)[0]:
                gram, _, _ = system(
                    rig0,
                    table,
                    cfg,
                    PixelEvents(
                        jnp.asarray(b.t_us[i]),
                        jnp.asarray(b.polarity[i]),
                        jnp.asarray(b.mask[i]),
                        jnp.asarray(offsets[b.column[i]]),
                        rig0.threshold_on,
                        rig0.threshold_off,
                        0.0,
                    ),
                    2,
                    return_gram=True,
                )
                xa = np.append(truth[b.pixel[i]], 1.0)
                per_event = float(xa @ np.asarray(gram) @ xa) / b.count[i]
                assert per_event < 1e-4  # relative residual ≲ 1 % per event


def test_chunking_does_not_change_the_result():
    # In float64, so the comparison is not blurred by float32 rounding (the QPs are
    # ill-conditioned: batching changes float32 results at the 1e-3 level).
    with jax.enable_x64(True):
        rig = ev.Rig()
        scene = ev.load_scene("colorchecker", (4, 6))
        events = ev.simulate(scene, rig, sweeps=1, key=jr.key(3))
        a = ev.reconstruct(events, rig, chunk_pixels=2048)
        b = ev.reconstruct(events, rig, chunk_pixels=16, sub_batch=8)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_device_grouping_gives_the_host_batches(capture, monkeypatch):
    # The accelerator's grouping (events sorted by pixel and batches gathered on the
    # device) must hand the solve the very inputs of the host grouping: the same
    # cube bit for bit, over several buckets and chunks; with carried references
    # (a float32 clock shift) within a rounding.
    from evhsi_jax._reconstruct import _pipeline, _pixels

    rig, _, events, info = capture
    kw = dict(threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off,
              backend="jax", chunk_pixels=32, sub_batch=8, return_info=True,
              sweep_speed="off")  # fmt: skip
    calls = []
    real = _pixels.DeviceLists.batch
    monkeypatch.setattr(_pixels.DeviceLists, "batch",
                        lambda self, *a: calls.append(a[1]) or real(self, *a))  # fmt: skip
    cubes, infos = [], []
    rng = np.random.default_rng(0)
    t0 = float(events.trigger_t_us[0])
    ref = t0 - rng.uniform(0.0, float(rig.period_us), SIZE)
    ref[rng.random(SIZE) < 0.3] = np.nan
    for refs in (None, ref):
        for where in (False, True):
            monkeypatch.setattr(_pipeline, "DEVICE_GROUPING", where)
            cube, inf = ev.reconstruct(events, rig, reference_us=refs, **kw)
            cubes.append(cube)
            infos.append(inf)
    assert len(set(calls)) >= 2  # the device path ran, with several bucket sizes
    np.testing.assert_array_equal(cubes[0], cubes[1])
    np.testing.assert_array_equal(infos[0].events, infos[1].events)
    np.testing.assert_array_equal(infos[0].kkt, infos[1].kkt)
    # A chunk with a non-finite answer takes the host's route back into the cube.
    monkeypatch.setattr(_pipeline, "DEVICE_GROUPING", True)
    monkeypatch.setattr(_pipeline, "_any_failed", lambda x, pixel: True)
    np.testing.assert_array_equal(ev.reconstruct(events, rig, **kw)[0], cubes[0])
    assert not np.array_equal(cubes[0], cubes[2])  # the references changed the answer
    # float32 rounding of the shifted times, through an ill-conditioned float32 solve
    assert ev.metrics.sam_map_deg(cubes[2], cubes[3]).max() < 0.05
    np.testing.assert_allclose(cubes[2], cubes[3], atol=1e-3)
    # White-reference gains: applied on the device before its clipping, as here.
    gained = rig.replace_host(channel_gain=np.linspace(0.15, 1.4, rig.channels))
    per_place = []
    for where in (False, True):
        monkeypatch.setattr(_pipeline, "DEVICE_GROUPING", where)
        per_place.append(ev.reconstruct(events, gained, **kw)[0])
    np.testing.assert_array_equal(per_place[0], per_place[1])
    assert per_place[0].max() == np.float32(
        ev.reconstruction.ProblemConfig().max_reflectance
    )
    # The mirror-speed estimate: the same factor from the host's lists of the
    # candidate pixels as from all of them (unshrunk here: this sensor has no mirror
    # jitter, and the shrunk factor would be 1); the times moved on the device
    # within a float32 rounding of the host's float64 move.
    from evhsi_jax._reconstruct import _sweep_speed

    monkeypatch.setattr(_sweep_speed, "SPEED_BIAS", 0.0)
    kw["sweep_speed"] = "auto"
    per_place = []
    for where in (False, True):
        monkeypatch.setattr(_pipeline, "DEVICE_GROUPING", where)
        per_place.append(ev.reconstruct(events, rig, **kw))
    (c_host, i_host), (c_dev, i_dev) = per_place
    assert i_host.sweep_speed[0] != 1.0
    np.testing.assert_array_equal(i_host.sweep_speed, i_dev.sweep_speed)
    # One float32 ulp of an event's time moves an ill-conditioned pixel of this float32
    # JAX path by up to ~0.1° (on an AVX2 CPU one of the 96 pixels moved 0.12°, and
    # the device's answer was the nearer to the fused backend's float64 one: 0.017°
    # against the host's 0.110°); the rest stay at the rounding level.
    sam = ev.metrics.sam_map_deg(c_host, c_dev)
    assert sam.max() < 0.25 and np.median(sam) < 0.01 and (sam < 0.1).mean() >= 0.95
    np.testing.assert_allclose(c_host, c_dev, atol=3e-3)  # that pixel's red end: 1.3e-3


def test_device_finish_is_the_hosts():
    # `_finish_on_device` must give what the host's NumPy passes give: non-finite
    # answers replaced and flagged, the inverse gains applied, the clip.
    from evhsi_jax._reconstruct._pipeline import _finish_on_device

    rng = np.random.default_rng(1)
    cube = rng.uniform(-0.5, 2.5, (50, 7)).astype(np.float32)
    cube[3, 2], cube[9, 0], cube[9, 6], cube[20, 4] = np.nan, np.inf, -np.inf, np.nan
    kkt = rng.uniform(0, 1e-3, 50).astype(np.float32)
    gain = rng.uniform(0.5, 1.5, 7).astype(np.float32)
    for g, clip in ((gain, 1.5), (None, None), (gain, None)):
        want, want_k = cube.copy(), kkt.copy()
        bad = ~np.isfinite(want)
        want[bad] = 0.04
        want_k[bad.any(axis=1)] = np.inf
        if g is not None:
            want = want * g
        if clip is not None:
            want = np.clip(want, 0.0, clip)
        got, got_k = _finish_on_device(
            jnp.asarray(cube), jnp.asarray(kkt), 0.04, g, clip
        )
        np.testing.assert_array_equal(np.asarray(got), want)
        np.testing.assert_array_equal(np.asarray(got_k), want_k)


def test_device_fill_and_deblur_are_the_hosts(capture, monkeypatch):
    # With the grouping on the device the hot pixels' fill, the deblurring and the
    # clip run there too: the fill gives the host's values bit for bit (medians of
    # the same neighbours, taken on the host), the deblurring the host's filter up
    # to the FFTs' float32 rounding.
    from evhsi_jax._reconstruct import _pipeline
    from evhsi_jax._reconstruct._deblur import deblur_cube, deblur_cube_device

    rng = np.random.default_rng(4)
    h, w, m = 9, 11, 6
    cube = rng.uniform(0.0, 1.0, (h, w, m)).astype(np.float32)
    hot = np.zeros((h, w), bool)
    hot[0, 0] = hot[4, 5] = hot[8, 10] = True  # corners and the middle
    hot[3:6, 1:4] = True  # a pixel (4, 2) whose neighbours are all hot
    counts = np.ones((h, w), np.int64)
    counts[7, 9] = 0  # a neighbour without events does not count
    want = _pipeline._fill_from_neighbours(cube, hot, counts)
    got = _pipeline._fill_from_neighbours_device(
        jnp.asarray(cube.reshape(h * w, m)), hot, counts
    )
    np.testing.assert_array_equal(np.asarray(got).reshape(h, w, m), want)
    assert not np.array_equal(want, cube)
    # By hand: (4, 5) from its 8 neighbours; (4, 2), all of whose neighbours are
    # hot, from every solved pixel that is not hot; the corner (8, 10) from its 3
    # neighbours less (7, 9), which has no events. The other pixels stay.
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    np.testing.assert_array_equal(want[4, 5], np.median(cube[3:6, 4:7][ring], axis=0))
    good = ~hot & (counts > 0)
    np.testing.assert_array_equal(want[4, 2], np.median(cube[good], axis=0))
    corner = good[7:9, 9:11]
    assert corner.sum() == 2
    np.testing.assert_array_equal(want[8, 10], np.median(cube[7:9, 9:11][corner], axis=0))
    np.testing.assert_array_equal(want[~hot], cube[~hot])
    blur = deblur_cube(want, 0.7)
    dev = np.asarray(deblur_cube_device(jnp.asarray(want), 0.7))
    np.testing.assert_allclose(dev, blur, atol=2e-6, rtol=0)
    assert np.abs(blur - want).max() > 0.05  # the filter does something
    clipped = np.asarray(deblur_cube_device(jnp.asarray(want), 0.7, clip_max=0.9))
    np.testing.assert_allclose(clipped, np.clip(blur, 0.0, 0.9), atol=2e-6, rtol=0)
    # The whole call: a calibration with a blur and hot pixels, both routes.
    rig, _, events, info = capture
    hot_map = np.zeros(SIZE, bool)
    hot_map[2, 3] = hot_map[5, 7] = True
    cal = ev.Calibration(rig.replace_host(psf_sigma_px=0.6), info.threshold_on,
                         info.threshold_off, hot_map)  # fmt: skip
    cubes = []
    for where in (False, True):
        monkeypatch.setattr(_pipeline, "DEVICE_GROUPING", where)
        cubes.append(ev.reconstruct(events, cal, backend="jax", chunk_pixels=32,
                                    sub_batch=8, sweep_speed="off"))  # fmt: skip
    np.testing.assert_allclose(cubes[1], cubes[0], atol=5e-6, rtol=0)
    assert cubes[1].max() <= ev.reconstruction.ProblemConfig().max_reflectance


def test_no_recompilation_on_second_call(capture):
    rig, _, events, _ = capture
    ev.reconstruct(events, rig)
    before = _solve_chunk._cached._cache_size()
    ev.reconstruct(events, rig)
    assert _solve_chunk._cached._cache_size() == before


def test_host_only_settings_do_not_recompile(capture):
    # Seeds, simulation spreads and rates, the gain and the sensor's noise values are
    # host-side settings or dynamic arrays: changing them must not key the jit cache.
    rig, _, events, _ = capture
    noisy = ev.Rig(threshold_noise=0.01)
    ev.reconstruct(events, noisy)
    before = _solve_chunk._cached._cache_size()
    for r in (
        ev.Rig(threshold_noise=0.02, timestamp_jitter_us=3.0, seed=5),
        ev.Rig(threshold_noise=0.01, noise_rate_hz=2.0, threshold_sigma=0.03),
        ev.Rig(threshold_noise=0.01, hot_pixel_fraction=0.01, channel_gain=[1.1] * 72),
    ):
        ev.reconstruct(events, r)
    assert _solve_chunk._cached._cache_size() == before


def test_buckets_follow_each_pixels_event_count(capture):
    _, _, events, _ = capture
    batches, counts, _ = group_pixels(
        events, t_start_us=0, chunk_pixels=64, min_chunk=16
    )
    seen = {}
    for b in batches:
        k = b.t_us.shape[1]
        for p, c in zip(b.pixel, b.count):
            if p >= 0:
                seen[p] = (k, c)
    assert set(seen) == set(
        np.nonzero(counts)[0]
    )  # no pixel twice, none without events
    for k, c in seen.values():
        assert c <= k and (k == 16 or c > k // 2)  # smallest bucket that fits


@pytest.mark.parametrize("max_events", [None, 5])
def test_grouping_kernels_match_the_numpy_reference(capture, max_events):
    # The numba counting sort and slot filling must give the NumPy path's batches bit
    # for bit (order within a pixel kept, padding, truncation to max_events).
    from evhsi_jax._base._numba import numba_available, use_backend

    if not numba_available():
        pytest.skip("numba is not importable here")
    _, _, events, _ = capture
    kw = dict(t_start_us=3, chunk_pixels=32, min_chunk=8, max_events=max_events)
    with use_backend("numpy"):
        ref, counts_ref, _ = group_pixels(events, **kw)
    with use_backend("numba"):
        got, counts, _ = group_pixels(events, **kw)
    np.testing.assert_array_equal(counts, counts_ref)
    assert len(got) == len(ref)
    for a, b in zip(got, ref):
        for f in ("pixel", "column", "t_us", "polarity", "mask", "count"):
            x, y = getattr(a, f), getattr(b, f)
            assert x.dtype == y.dtype and x.shape == y.shape, f
            np.testing.assert_array_equal(x, y, err_msg=f)


@pytest.mark.parametrize("slice_events", [1 << 21, 97])
def test_screening_kernel_matches_the_numpy_reference(slice_events, monkeypatch):
    # Background events, hot pixels and jitter, recording started mid-period: the
    # numba screening must keep and flag exactly what the NumPy code does, also cut
    # into slices screened on several threads.
    from evhsi_jax._base._numba import numba_available, use_backend
    from evhsi_jax._reconstruct import _pipeline
    from evhsi_jax._reconstruct._pipeline import noise_model, screen_events

    monkeypatch.setattr(_pipeline, "SCREEN_SLICE", slice_events)

    if not numba_available():
        pytest.skip("numba is not importable here")
    rig = ev.Rig(noise_rate_hz=40.0, hot_pixel_fraction=0.05, timestamp_jitter_us=5.0)
    events = ev.simulate(ev.load_scene("colorchecker", SIZE), rig, sweeps=2,
                         key=jr.key(4))  # fmt: skip
    for start in (0, 1234):
        args = (events.time_window(start, 10**9), rig, start, noise_model(rig), 2)
        with use_backend("numpy"):
            ref = screen_events(*args)
        with use_backend("numba"):
            got = screen_events(*args)
        assert got[2] == ref[2] > 0  # the same number dropped
        np.testing.assert_array_equal(got[1], ref[1])
        for f in ("x", "y", "p", "t_us"):
            np.testing.assert_array_equal(getattr(got[0], f), getattr(ref[0], f))


def test_device_lists_drop_the_screened_events_themselves():
    # The device's grouping takes the screening's mask instead of the kept events
    # (no host copy of 25 M events): the events it drops sort past the last pixel,
    # and every pixel's list is the one of the screened stream.
    from evhsi_jax._reconstruct._pipeline import (
        _screen_mask,
        noise_model,
        screen_events,
    )
    from evhsi_jax._reconstruct._pixels import DeviceLists

    rig = ev.Rig(noise_rate_hz=40.0, hot_pixel_fraction=0.05, timestamp_jitter_us=5.0)
    events = ev.simulate(ev.load_scene("colorchecker", SIZE), rig, sweeps=2,
                         key=jr.key(5))  # fmt: skip
    args = (events, rig, 0, noise_model(rig), 2)
    keep, n_kept, hot, dropped = _screen_mask(*args)
    kept, hot_ref, dropped_ref = screen_events(*args)
    assert keep is not None and dropped == dropped_ref > 0 and hot.any()
    np.testing.assert_array_equal(hot, hot_ref)
    assert n_kept == len(kept)
    a, b = DeviceLists(events, 0, keep), DeviceLists(kept, 0)
    np.testing.assert_array_equal(a.counts, b.counts)
    assert a.counts.sum() == n_kept
    np.testing.assert_array_equal(np.asarray(a.starts), np.asarray(b.starts))
    for f in ("t_sorted", "s_sorted"):
        np.testing.assert_array_equal(
            np.asarray(getattr(a, f))[:n_kept], np.asarray(getattr(b, f))[:n_kept]
        )


def test_batch_sizes_follow_the_device_kind():
    from evhsi_jax._reconstruct._pipeline import (
        ACCELERATOR_BATCH,
        CPU_BATCH,
        batch_sizes,
    )

    assert batch_sizes(None, None) == CPU_BATCH  # the suite runs on a CPU
    assert batch_sizes(100, None) == (100, 100)  # the sub-batch never exceeds a chunk
    assert batch_sizes(None, 7) == (CPU_BATCH[0], 7)
    assert ACCELERATOR_BATCH[0] > CPU_BATCH[0]
    with pytest.raises(ValueError, match=">= 1"):
        batch_sizes(0, None)


def _single_pixel_events(times, pols, width=1, height=1):
    return ev.EventStream(
        x=np.zeros(len(times), int),
        y=np.zeros(len(times), int),
        p=(np.asarray(pols) > 0).astype(int),
        t_us=np.asarray(times, np.int64),
        width=width,
        height=height,
    )


@pytest.mark.parametrize(
    "times,pols",
    [
        ([], []),
        ([5000], [1]),
        ([5000, 9000], [1, -1]),
        ([4000, 4500, 5200, 6100], [1] * 4),
    ],
    ids=["0-events", "1-event", "2-events", "only-ON"],
)
@pytest.mark.parametrize("solver", ["auto", "boxcdqp", "svd", "apg"])
def test_degenerate_event_lists_give_finite_nonnegative_spectra(times, pols, solver):
    rig = ev.Rig()
    stream = _single_pixel_events(times, pols)
    cube = ev.reconstruct(stream, rig, solver=solver) if times else None
    if not times:  # every pixel gets the flat no-event answer, no solve
        empty = ev.reconstruct(ev.EventStream([], [], [], [], width=2, height=1), rig)
        cube = ev.reconstruct(_single_pixel_events([5000], [1], width=2), rig)
        flat = cube[0, 1, 0]
        assert 0 < flat < 0.01 and np.all(cube[0, 1] == flat) and np.all(empty == flat)
    assert np.all(np.isfinite(cube))
    if solver != "svd":  # the paper's SVD baseline is unconstrained by design
        assert np.all(cube >= 0)


@pytest.mark.parametrize("kind", ["white", "black", "laser", "dark"])
def test_hard_spectra_are_finite_and_nonnegative(kind):
    wl = np.arange(380.0, 781.0, 1.0)
    spec = {
        "white": np.ones_like(wl),
        "black": np.zeros_like(wl),
        "laser": np.where(np.abs(wl - 532.5) <= 2.5, 1.0, 0.0),
        "dark": np.full_like(wl, 0.004),
    }[kind]
    scene = ev.Scene(spec[None, :], wl, np.zeros((2, 3), int))
    rig = ev.Rig()
    events = ev.simulate(scene, rig, sweeps=1, key=jr.key(0))
    if len(events) == 0:
        assert kind in ("black", "dark")
        return
    cube = ev.reconstruct(events, rig)
    assert np.all(np.isfinite(cube)) and np.all(cube >= 0)
    if kind == "laser":  # the energy sits at the line, not elsewhere
        wl_c = rig.wavelengths_nm
        peak = wl_c[np.argmax(cube.mean((0, 1)))]
        assert abs(peak - 532.5) <= 10


def test_reconstruction_gradients_match_finite_differences():
    with jax.enable_x64(True):
        rig = ev.Rig(threshold_sigma=0.0)
        scene = ev.load_scene("colorchecker", (2, 3))
        events = ev.simulate(scene, rig, sweeps=1, key=jr.key(0))
        b = group_pixels(events, t_start_us=0, chunk_pixels=8)[0][0]
        sel = np.nonzero(b.pixel >= 0)[0]
        args = (
            jnp.asarray(b.t_us[sel]),
            jnp.asarray(b.polarity[sel], jnp.int32),
            jnp.asarray(b.mask[sel]),
            jnp.asarray(b.column[sel]),
        )
        truth = scene.truth_cube(rig.grid).reshape(-1, rig.channels)[b.pixel[sel]]
        truth = jnp.asarray(truth, jnp.float64)

        @eqx.filter_jit  # compiled once for the 8 finite-difference evaluations
        def loss(r):
            x = reconstruct_pixels(r, *args, width=3, fwhm_bound_nm=50.0)
            return jnp.mean((x - truth) ** 2)

        grad = eqx.filter_jit(eqx.filter_grad(loss))(rig)
        for name in ("beta_nm_per_rad", "threshold_on", "baseline_rel", "fwhm_nm"):
            v = float(getattr(rig, name))
            h = 1e-6 * max(abs(v), 1.0)

            def at(val, name=name):
                return loss(
                    eqx.tree_at(lambda r: getattr(r, name), rig, jnp.asarray(val))
                )

            fd = (at(v + h) - at(v - h)) / (2 * h)
            g = float(getattr(grad, name))
            assert np.isfinite(g)
            assert g == pytest.approx(float(fd), rel=2e-3, abs=1e-12), name


def test_problem_config_validation():
    with pytest.raises(ValueError, match="int_target"):
        ProblemConfig(int_target="cubic")
    with pytest.raises(ValueError):
        ProblemConfig(alpha_int=-1.0)
    assert dataclasses.replace(ProblemConfig(), alpha_spec=0.5).alpha_spec == 0.5


def test_threshold_map_shape_is_checked(capture):
    rig, _, events, _ = capture
    with pytest.raises(ValueError, match="shape"):
        ev.reconstruct(events, rig, threshold_on_map=np.full((3, 3), 0.15))


def test_failed_batched_solves_are_resolved_exactly(
    capture, cube_known_thresholds, monkeypatch
):
    """A pixel whose batched solve comes out non-finite (a float32 Cholesky failure on
    a rounding-indefinite system) is re-solved one by one with the shifted-retry
    factorisation, not replaced by the flat no-event answer."""
    from evhsi_jax._reconstruct import _pipeline

    rig, _, events, info = capture
    ref, ref_info = cube_known_thresholds
    real = _pipeline._solve_chunk

    def failing(*a, **k):
        x, kkt = real(*a, **k)
        x = np.array(x)
        x[[0, 5]] = np.nan  # two pixels of every chunk "fail"
        return jnp.asarray(x), kkt

    monkeypatch.setattr(_pipeline, "_solve_chunk", failing)
    cube, got = ev.reconstruct(
        events,
        rig,
        threshold_on_map=info.threshold_on,
        threshold_off_map=info.threshold_off,
        return_info=True,
    )
    assert np.all(np.isfinite(cube)) and np.all(np.isfinite(got.kkt[got.solved]))
    np.testing.assert_allclose(cube, ref, atol=1e-4)
    assert np.max(got.kkt[got.solved]) < 1e-4


def test_pixel_lists_kernel_matches_the_numpy_reference(capture):
    # The one-pass numba fill of every pixel's event list (the fused backend's input)
    # must give the NumPy path's counts, starts, times and polarities bit for bit.
    from evhsi_jax._base._numba import numba_available, use_backend
    from evhsi_jax._reconstruct._pixels import pixel_lists

    if not numba_available():
        pytest.skip("numba is not importable here")
    _, _, events, _ = capture
    with use_backend("numpy"):
        ref = pixel_lists(events, 3)
    with use_backend("numba"):
        got = pixel_lists(events, 3)
    for a, b in zip(got, ref):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    # Its passes split over threads (every core, from THREADED_LISTS_MIN events on):
    # the same arrays, also with slices and block ranges that do not divide evenly.
    import concurrent.futures

    from evhsi_jax._reconstruct import _group_jit
    from evhsi_jax._reconstruct._pixels import TIMESTAMP_CENTRE_US

    w, h = events.width, events.height
    args = (events.x, events.y, events.t_us, events.p, np.int64(w), np.int64(w * h),
            np.int64(3), TIMESTAMP_CENTRE_US)  # fmt: skip
    for workers in (2, 3):
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            *par, far = _group_jit.pixel_lists_threaded(*args, pool, workers)
        assert far == 0
        for a, b in zip(par, ref, strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


def test_pixel_lists_far_apart_times_take_the_numpy_path(monkeypatch):
    # The numba lists pack each event's time from the start into 45 bits; times
    # further apart (here ±2^46 µs, and one negative) are flagged by both numba
    # routes and listed by the NumPy path instead: the reference arrays.
    from evhsi_jax._base._numba import numba_available, use_backend
    from evhsi_jax._reconstruct import _group_jit, _pixels

    if not numba_available():
        pytest.skip("numba is not importable here")
    t = np.array([-(1 << 46), 5, 7, 9, 11, 1 << 46, (1 << 46) + 3], np.int64)
    n = t.size
    events = ev.io.EventStream(
        x=np.array([0, 1, 0, 2, 1, 0, 2], np.uint16), y=np.zeros(n, np.uint16),
        p=np.array([1, 0, 1, 1, 0, 0, 1], np.uint8), t_us=t, width=3, height=1,
    )  # fmt: skip
    args = (events.x, events.y, events.t_us, events.p, np.int64(3), np.int64(3),
            np.int64(0), _pixels.TIMESTAMP_CENTRE_US)  # fmt: skip
    assert _group_jit.pixel_lists(*args)[4] == 3
    with use_backend("numpy"):
        ref = _pixels.pixel_lists(events, 0)
    for threaded in (False, True):
        monkeypatch.setattr(_pixels, "THREADED_LISTS_MIN", 1 if threaded else 1 << 30)
        monkeypatch.setattr(_pixels.shard, "usable_cores", lambda: 2)
        with use_backend("numba"):
            got = _pixels.pixel_lists(events, 0)
        for a, b in zip(got, ref, strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    # Within the span, the numba route's own arrays: the same as the reference.
    near = ev.io.EventStream(
        x=events.x[1:5], y=events.y[1:5], p=events.p[1:5], t_us=t[1:5], width=3,
        height=1,
    )  # fmt: skip
    with use_backend("numpy"):
        ref = _pixels.pixel_lists(near, 0)
    *got, far = _group_jit.pixel_lists(*((near.x, near.y, near.t_us, near.p) + args[4:]))
    assert far == 0
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a, b)


def test_device_lists_padding_threaded_is_serial(monkeypatch):
    # DeviceLists' host-side arrays, filled in slices on several threads from
    # THREADED_LISTS_MIN events on: the same arrays as one thread's, padding
    # included, for a count that is not a multiple of anything.
    from evhsi_jax._base import shard
    from evhsi_jax._reconstruct import _pixels

    rng = np.random.default_rng(2)
    n, w, h = 5003, 40, 30
    events = ev.io.EventStream(
        x=rng.integers(0, w, n).astype(np.uint16), y=rng.integers(0, h, n).astype(np.uint16),
        p=rng.integers(0, 2, n).astype(np.uint8),
        t_us=np.sort(rng.integers(1000, 90_000, n)).astype(np.int64), width=w, height=h,
    )  # fmt: skip
    monkeypatch.setattr(shard, "usable_cores", lambda: 3)
    monkeypatch.setattr(_pixels, "THREADED_LISTS_MIN", 1 << 30)
    serial = _pixels._padded_for_device(events, 1000)
    monkeypatch.setattr(_pixels, "THREADED_LISTS_MIN", 1000)
    threaded = _pixels._padded_for_device(events, 1000)
    assert serial[0].size == 8192
    for a, b in zip(threaded, serial):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert np.all(serial[1][n:] == h) and np.all(serial[2][:n] == events.t_us - 1000)


def test_cube_comes_home_whole_and_writable(monkeypatch):
    # The accelerator's route of a cube to the host (pinned host memory, then a copy
    # in slices on several threads), run here on the CPU: the same values, a new
    # writable array, for sizes that do not divide into the slices.
    from evhsi_jax._base import shard

    monkeypatch.setattr(shard, "usable_cores", lambda: 3)
    monkeypatch.setattr(shard, "PINNED_MIN_BYTES", 1000)
    rng = np.random.default_rng(4)
    for shape in ((101, 7), (5,), (37, 73)):
        a = jnp.asarray(rng.standard_normal(shape), jnp.float32)
        for pinned in (True, False, None):
            got = shard.to_host_copy(a, via_pinned=pinned)
            assert got.flags.writeable and got.shape == shape and got.dtype == a.dtype
            np.testing.assert_array_equal(got, np.asarray(a))
            got[...] = 0  # its own memory: the device array is untouched
            assert np.asarray(a).any()

    # A device (or JAX) without pinned host memory: the plain copy.
    def no_pinned(*args, **kw):
        raise ValueError("memory kind pinned_host is not supported")

    monkeypatch.setattr(shard.jax, "device_put", no_pinned)
    got = shard.to_host_copy(a, via_pinned=True)
    assert got.flags.writeable
    np.testing.assert_array_equal(got, np.asarray(a))


def test_anti_drift_weight_is_for_the_whole_recording():
    """`alpha_int` weighs the anti-drift prior over the whole recording: each of S
    sweeps gets alpha_int / S, so the prior does not grow with the data. An ideal
    sensor, the training scene `tcs`, 4 sweeps, true maps: the old weighting (each
    sweep the whole weight, `alpha_int × S` here) is the less accurate (32×48 in
    `experiments/anti_drift_sweeps.py`: 0.75° against 0.61°)."""
    from evhsi_jax.reconstruction import ProblemConfig

    rig = ev.Rig()
    scene = ev.load_scene("tcs", (16, 24))
    truth = scene.truth_cube(rig.grid)
    events, info = ev.simulate(scene, rig, sweeps=4, key=jr.key(5), return_info=True)
    cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
    alpha = ProblemConfig().alpha_int
    sam = {
        a: ev.evaluate(ev.reconstruct(events, cal, config=ProblemConfig(alpha_int=a)),
                       truth)["sam_deg"]
        for a in (alpha, 4 * alpha)
    }  # fmt: skip
    assert sam[alpha] < 0.95 * sam[4 * alpha], sam
