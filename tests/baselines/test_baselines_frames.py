"""Frame-camera baseline: forward operator, capture, bandwidth matching, recovery."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
import scipy.optimize

import evhsi_jax as ev
from evhsi_jax._baselines import (
    FrameOperator,
    capture_frames,
    frame_intensity,
    frame_times_us,
    matched_frame_count,
    nonneg_lsq_shared,
    reconstruct_frames,
)


@pytest.fixture(scope="module")
def rig():
    return ev.Rig()


def test_frame_times_are_a_uniform_subset_of_the_full_grid(rig):
    full = frame_times_us(rig, rig.samples_per_sweep)
    period = float(rig.period_us)
    np.testing.assert_allclose(full, np.arange(1200) * period / 1200)
    sub = frame_times_us(rig, 300)
    np.testing.assert_allclose(sub, full[::4])
    odd = frame_times_us(rig, 7)
    assert np.all(np.isin(odd, full)) and odd.size == 7
    with pytest.raises(ValueError, match="frames must be"):
        frame_times_us(rig, 1201)


def test_frame_operator_adjoint_float64():
    with jax.enable_x64(True):
        rig = ev.Rig(channels=12)
        t = frame_times_us(rig, 40)
        op = FrameOperator.from_rig(rig, t, 5)
        assert op.table.dtype == jnp.float64
        x = jr.normal(jr.key(0), (3, 5, 12), jnp.float64)
        y = jr.normal(jr.key(1), (40, 3, 5), jnp.float64)
        lhs = jnp.vdot(op(x), y)
        rhs = jnp.vdot(x, op.adjoint(y))
        np.testing.assert_allclose(float(lhs), float(rhs), rtol=1e-12)
        assert abs(float(lhs)) > 1e-3  # a non-trivial product


def test_fine_grid_frames_match_channel_operator_on_channel_constant_scene(rig):
    # Spectra constant within each 5 nm channel: the simulator's fine table and the
    # channel table must then give the same intensities (up to the 1e-4 nm ramps).
    rng = np.random.default_rng(0)
    edges = rig.grid.edges_nm
    wl = np.sort(np.r_[edges[:-1] + 1e-4, edges[1:] - 1e-4, 380.0, 780.0])
    vals = rng.uniform(0.05, 0.95, (3, rig.channels))
    # Piecewise constant: each sample takes its channel's value.
    chan = np.clip(np.searchsorted(edges, wl, side="right") - 1, 0, rig.channels - 1)
    pal = vals[:, chan]
    labels = np.array([[0, 1, 2, 0], [2, 1, 0, 1]])
    scene = ev.Scene(pal, wl, labels)
    t = frame_times_us(rig, 200)
    fine = np.asarray(frame_intensity(scene, rig, t))
    op = FrameOperator.from_rig(rig, t, scene.width)
    chan_cube = jnp.asarray(vals[labels], jnp.float32)
    ref = np.asarray(op(chan_cube)) + float(rig.baseline_rel)
    assert fine.shape == (200, 2, 4)
    np.testing.assert_allclose(fine, ref, atol=2e-4 * fine.max())
    assert fine.max() > 0.3  # the band really crossed the pixels


def test_capture_quantises_to_the_peak_without_noise(rig):
    scene = ev.load_scene("colorchecker", (4, 6))
    stack = capture_frames(scene, rig, frames=120, noise_sigma=0.0, key=jr.key(0))
    assert stack.frames.dtype == np.uint8 and stack.frames.shape == (120, 4, 6)
    assert stack.frames.max() == 255
    clean = np.asarray(frame_intensity(scene, rig, stack.t_us))
    np.testing.assert_allclose(clean.max(), stack.full_scale, rtol=1e-6)
    err = np.abs(stack.intensity() - clean).max()
    assert err <= 0.5 * stack.full_scale / 255 * 1.0001
    assert stack.nbytes == 120 * 4 * 6


def test_noise_is_multiplicative_with_the_given_sigma(rig):
    scene = ev.load_scene("gray-chart", (6, 8))
    kw = dict(frames=600, bits=16, key=jr.key(3))
    clean = capture_frames(scene, rig, noise_sigma=0.0, **kw).intensity()
    noisy = capture_frames(
        scene, rig, noise_sigma=0.067, full_scale=float(clean.max()), **kw
    )
    bright = clean > 0.3 * clean.max()
    ratio = noisy.intensity()[bright] / clean[bright] - 1.0
    assert abs(ratio.std() - 0.067) < 0.005
    assert abs(ratio.mean()) < 0.005


def test_matched_frame_count():
    # 1000 events at 16 bits = 2000 bytes; a 10 × 10 8-bit frame is 100 bytes.
    assert matched_frame_count(1000, 10, 10) == 20
    assert matched_frame_count(1000, 10, 10, sweeps=4) == 5
    assert matched_frame_count(1, 100, 100) == 1  # never zero frames
    ev_stream = ev.EventStream(
        x=np.zeros(50, np.uint16),
        y=np.zeros(50, np.uint16),
        p=np.ones(50, np.uint8),
        t_us=np.arange(50, dtype=np.int64),
        width=5,
        height=2,
    )
    assert matched_frame_count(ev_stream) == 10
    with pytest.raises(ValueError, match="width and height"):
        matched_frame_count(10)


def test_shared_nnls_matches_scipy():
    with jax.enable_x64(True):
        rng = np.random.default_rng(1)
        g = rng.normal(size=(40, 8)) * np.geomspace(1, 0.05, 8)  # uneven scaling
        b = rng.normal(size=(6, 40))
        x = np.asarray(
            nonneg_lsq_shared(jnp.asarray(g.T @ g), jnp.asarray(b @ g), iters=3000)
        )
    ref = np.stack([scipy.optimize.nnls(g, bi)[0] for bi in b])
    assert np.any(ref == 0) and np.any(ref > 0)  # the bound is active somewhere
    np.testing.assert_allclose(x, ref, atol=1e-6)


def test_noiseless_full_bandwidth_frames_recover_the_truth(rig):
    scene = ev.load_scene("colorchecker", (4, 6))
    truth = scene.truth_cube(rig.grid)
    stack = capture_frames(
        scene,
        rig,
        frames=rig.samples_per_sweep,
        noise_sigma=0.0,
        bits=16,
        key=jr.key(0),
    )
    cube = reconstruct_frames(stack, rig, alpha_spec=1e-4, iters=3000)
    assert cube.shape == truth.shape and cube.dtype == np.float32
    assert ev.metrics.sam_deg(cube, truth) < 0.5
    assert ev.metrics.psnr_db(cube, truth) > 45.0


def test_few_frames_lose_accuracy(rig):
    # The frame baseline must degrade when frames are scarce (otherwise the bandwidth
    # study would be meaningless).
    scene = ev.load_scene("colorchecker", (4, 6))
    truth = scene.truth_cube(rig.grid)
    kw = dict(noise_sigma=0.0, bits=16, key=jr.key(0))
    many = reconstruct_frames(capture_frames(scene, rig, frames=600, **kw), rig)
    few = reconstruct_frames(capture_frames(scene, rig, frames=20, **kw), rig)
    assert ev.metrics.sam_deg(few, truth) > 2 * ev.metrics.sam_deg(many, truth)


def test_exposure_averages_instantaneous_samples(rig):
    scene = ev.load_scene("colorchecker", (2, 3))
    t = frame_times_us(rig, 50)
    exp = float(rig.period_us) / 50
    avg = np.asarray(frame_intensity(scene, rig, t, exposure_us=exp, substeps=4))
    offs = (np.arange(4) + 0.5) / 4 - 0.5
    ref = np.mean(
        [np.asarray(frame_intensity(scene, rig, t + exp * o)) for o in offs], axis=0
    )
    np.testing.assert_allclose(avg, ref, rtol=1e-5, atol=1e-6)
    inst = np.asarray(frame_intensity(scene, rig, t))
    assert np.abs(avg - inst).max() > 1e-3  # the exposure does blur the trace
