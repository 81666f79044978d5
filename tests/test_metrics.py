"""Metrics against independent NumPy computations written here."""

import numpy as np
import pytest

from evhsi_jax import evaluate
from evhsi_jax.metrics import per_label_table, psnr_db, rms, sam_deg, ssim


@pytest.fixture
def cubes():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.05, 0.9, (6, 7, 10))
    est = np.clip(ref + 0.03 * rng.standard_normal(ref.shape), 0, None)
    return est, ref


def test_sam_matches_hand_computation(cubes):
    est, ref = cubes
    angles = []
    for e, r in zip(est.reshape(-1, 10), ref.reshape(-1, 10)):
        c = np.dot(e, r) / np.sqrt(np.dot(e, e) * np.dot(r, r))
        angles.append(np.degrees(np.arccos(min(1.0, c))))
    assert sam_deg(est, ref) == pytest.approx(np.mean(angles), rel=1e-12)


def test_sam_is_scale_invariant_and_zero_for_equal_shapes(cubes):
    _, ref = cubes
    assert sam_deg(3.0 * ref, ref) == pytest.approx(0.0, abs=1e-6)
    assert sam_deg(ref, ref) == pytest.approx(0.0, abs=1e-6)


def test_sam_zero_spectra():
    ref = np.ones((1, 2, 4))
    est = ref.copy()
    est[0, 0] = 0.0
    # One pixel has no angle (estimate all zero): counts as 90°, the other 0°.
    assert sam_deg(est, ref) == pytest.approx(45.0)
    assert sam_deg(np.zeros_like(ref), np.zeros_like(ref)) == 0.0


def test_psnr_and_rms_definitions(cubes):
    est, ref = cubes
    mse = np.sum((est - ref) ** 2) / est.size
    assert rms(est, ref) == pytest.approx(np.sqrt(mse), rel=1e-12)
    assert psnr_db(est, ref) == pytest.approx(10 * np.log10(1.0 / mse), rel=1e-12)
    assert psnr_db(ref, ref) == float("inf")
    # A uniform error of 0.1 is 20 dB for peak 1.
    assert psnr_db(ref + 0.1, ref) == pytest.approx(20.0, rel=1e-9)


def test_ssim_closed_forms():
    # Identical images: 1. Two constant images of means a, b: the variance terms vanish
    # and SSIM = (2ab + c1) / (a² + b² + c1), c1 = 0.01².
    a, b = 0.3, 0.6
    img_a = np.full((16, 16, 2), a)
    img_b = np.full((16, 16, 2), b)
    assert ssim(img_a, img_a) == pytest.approx(1.0)
    c1 = 1e-4
    assert ssim(img_a, img_b) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1))


def test_ssim_window_statistic_at_centre_pixel():
    # Independent check of the Gaussian-window statistics at the central pixel, away
    # from the borders (weights built here from the σ = 1.5, 11×11 definition).
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (31, 31))
    y = np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1)
    g = np.exp(-0.5 * (np.arange(-5, 6) / 1.5) ** 2)
    w = np.outer(g, g)
    w /= w.sum()
    sl = (slice(10, 21), slice(10, 21))
    mx, my = np.sum(w * x[sl]), np.sum(w * y[sl])
    sxx = np.sum(w * x[sl] ** 2) - mx**2
    syy = np.sum(w * y[sl] ** 2) - my**2
    sxy = np.sum(w * x[sl] * y[sl]) - mx * my
    c1, c2 = 1e-4, 9e-4
    want = (
        (2 * mx * my + c1) * (2 * sxy + c2) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    )
    from scipy import ndimage

    from evhsi_jax._base._metrics import _ssim_2d

    # Reproduce the map value at the centre through the library's filtered statistics.
    filt = lambda im: ndimage.gaussian_filter(im, 1.5, truncate=3.5, mode="reflect")  # noqa: E731
    mu_x, mu_y = filt(x)[15, 15], filt(y)[15, 15]
    assert mu_x == pytest.approx(mx, rel=1e-9) and mu_y == pytest.approx(my, rel=1e-9)
    s = (
        (2 * mu_x * mu_y + c1)
        * (2 * (filt(x * y)[15, 15] - mu_x * mu_y) + c2)
        / (
            (mu_x**2 + mu_y**2 + c1)
            * (filt(x * x)[15, 15] - mu_x**2 + filt(y * y)[15, 15] - mu_y**2 + c2)
        )
    )
    assert s == pytest.approx(want, rel=1e-9)
    assert 0 < _ssim_2d(x, y) < 1


def test_evaluate_keys_and_shape_errors(cubes):
    est, ref = cubes
    out = evaluate(est, ref)
    assert set(out) == {"sam_deg", "psnr_db", "ssim", "rms"}
    with pytest.raises(ValueError, match="shapes differ"):
        evaluate(est[:, :3], ref)
    with pytest.raises(ValueError, match="finite"):
        evaluate(np.full_like(ref, np.nan), ref)


def test_per_label_table(cubes):
    est, ref = cubes
    labels = np.zeros(ref.shape[:2], int)
    labels[:, 3:] = 1
    rows = per_label_table(est, ref, labels, ["left", "right"])
    assert [r["name"] for r in rows] == ["left", "right"]
    assert rows[0]["pixels"] == 18 and rows[1]["pixels"] == 24
    assert rows[1]["sam_deg"] == pytest.approx(sam_deg(est[:, 3:], ref[:, 3:]))
