"""Rendering cubes to sRGB, PNG files (atomic), and cube files."""

from __future__ import annotations

import warnings

import colour
import matplotlib.image
import numpy as np
import pytest

from evhsi_jax import Rig, cube_to_srgb, load_cube, load_scene, save_cube, write_png
from evhsi_jax._base._storage import atomic_write
from evhsi_jax.video import write_comparison_png

CENTRES = Rig().wavelengths_nm  # 402.5 … 757.5 nm, 5 nm channels


def channel_weights(centres, step=0.02):
    """∫ x̄ȳz̄(λ)·D65(λ) dλ over each channel, by a dense midpoint rule, normalised so
    that a perfect white over the CMFs' whole range has Y = 1; (M, 3)."""
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    wl, vals = np.asarray(cmfs.wavelengths), np.asarray(cmfs.values)

    def weighted(lam):
        s = np.interp(lam, d65.wavelengths, d65.values)
        return (
            np.stack([np.interp(lam, wl, vals[:, i]) for i in range(3)], -1)
            * s[:, None]
        )

    half = 0.5 * (centres[1] - centres[0])
    out = []
    for c in centres:
        lam = np.arange(c - half + step / 2, c + half, step)
        out.append(weighted(lam).sum(0) * step)
    lam = np.arange(wl[0] + step / 2, wl[-1], step)
    y_white = weighted(lam)[:, 1].sum() * step
    return np.array(out) / y_white


@pytest.fixture(scope="module")
def weights():
    return channel_weights(CENTRES)


def reference_srgb(spectra, weights):
    """Channel spectra (N, M) → sRGB by the weights above and colour-science's
    XYZ → sRGB (IEC 61966-2-1 matrix and transfer function), clipped."""
    xyz = spectra @ weights
    return np.clip(colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=True), 0, 1)


def test_white_renders_white(weights):
    rgb = cube_to_srgb(np.ones((2, 3, 72)), CENTRES)
    assert rgb.shape == (2, 3, 3) and rgb.dtype == np.float32
    np.testing.assert_allclose(rgb, 1.0, atol=0.01)
    # The 400-760 nm channels hold all but ~0.2 % of a white's luminance.
    y = weights[:, 1].sum()
    assert 0.995 < y < 1.0


@pytest.mark.parametrize("level", [0.0, 0.18, 0.5])
def test_gray_renders_neutral(level):
    rgb = cube_to_srgb(np.full((1, 1, 72), level), CENTRES)[0, 0]
    assert np.ptp(rgb) < 0.01
    # sRGB of a gray with luminance Y ≈ level (the transfer function, by hand).
    y = 0.998 * level
    v = 12.92 * y if y <= 0.0031308 else 1.055 * y ** (1 / 2.4) - 0.055
    np.testing.assert_allclose(rgb, v, atol=0.01)


@pytest.mark.parametrize(
    "patches", [["dark skin", "blue", "yellow"], ["red", "cyan", "neutral 5 (.70 D)"]]
)
def test_matches_independent_colour_computation(weights, patches):
    scene = load_scene("colorchecker", (4, 6))
    truth = scene.truth_cube(Rig().grid)  # channel averages of the measured spectra
    idx = [list(scene.names).index(p) for p in patches]
    spectra = truth.reshape(-1, 72)[
        [int(np.argmax(scene.labels.ravel() == k)) for k in idx]
    ]
    got = cube_to_srgb(spectra[None], CENTRES)[0]
    np.testing.assert_allclose(got, reference_srgb(spectra, weights), atol=2e-4)
    # And close to colour-science's own rendering of the measured spectra.
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    with warnings.catch_warnings():  # "aligning the illuminant to the CMFs' shape"
        warnings.simplefilter("ignore", colour.utilities.ColourRuntimeWarning)
        xyz = np.stack(
            [
                colour.sd_to_XYZ(sds[p], cmfs, colour.SDS_ILLUMINANTS["D65"]) / 100
                for p in patches
            ]
        )
    want = np.clip(colour.XYZ_to_sRGB(xyz), 0, 1)
    np.testing.assert_allclose(got, want, atol=0.02)


def test_nan_and_out_of_range():
    cube = np.zeros((1, 3, 72))
    cube[0, 0] = np.nan
    cube[0, 1] = 5.0
    cube[0, 2] = -1.0
    rgb = cube_to_srgb(cube, CENTRES)
    np.testing.assert_array_equal(rgb[0, 0], 0.0)
    np.testing.assert_array_equal(rgb[0, 1], 1.0)
    np.testing.assert_array_equal(rgb[0, 2], 0.0)


def test_float32_cube_and_non_finite_channels():
    """A float32 cube (weighed in float32) renders as its float64 copy to float32
    rounding; a pixel with a NaN or infinite channel renders as the float64 cube
    with NaN as 0 and ±inf as the largest finite numbers (`np.nan_to_num`)."""
    rng = np.random.default_rng(4)
    cube = rng.uniform(0.0, 1.2, (5, 6, 72)).astype(np.float32)
    cube[1, 2, 10] = np.nan
    cube[3, 4, 30] = np.inf
    cube[4, 5, 0] = -np.inf
    got = cube_to_srgb(cube, CENTRES)
    want = cube_to_srgb(np.nan_to_num(cube.astype(np.float64)), CENTRES)
    assert got.dtype == np.float32 and np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
    for y, x in ((1, 2), (3, 4), (4, 5)):  # (weighed in float64 on both routes)
        np.testing.assert_allclose(got[y, x], want[y, x], rtol=0, atol=1e-6)


def test_other_channel_grids(weights):
    """A coarser cube of the same spectra renders the same colour."""
    fine = np.random.default_rng(0).random(72)
    coarse = fine.reshape(36, 2).mean(1)
    a = cube_to_srgb(np.tile(fine, (1, 1, 1)), CENTRES)
    centres36 = CENTRES.reshape(36, 2).mean(1)
    b = cube_to_srgb(coarse[None, None], centres36)
    want = reference_srgb(coarse[None], channel_weights(centres36))[0]
    np.testing.assert_allclose(b[0, 0], want, atol=2e-4)
    np.testing.assert_allclose(a, b, atol=0.03)


def test_shape_mismatch():
    with pytest.raises(ValueError, match="72 wavelengths"):
        cube_to_srgb(np.zeros((2, 2, 71)), CENTRES)


# --- PNG files ------------------------------------------------------------------------


def test_png_round_trip(tmp_path):
    rgb = np.random.default_rng(1).random((5, 7, 3)).astype(np.float32)
    path = tmp_path / "out.png"
    write_png(path, rgb)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    back = matplotlib.image.imread(path)
    assert back.shape[:2] == (5, 7)
    np.testing.assert_allclose(back[..., :3], rgb, atol=1 / 255 + 1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["out.png"]  # no temporary left


def test_png_overwrite_and_bad_folder(tmp_path):
    path = tmp_path / "out.png"
    write_png(path, np.zeros((2, 2, 3)))
    write_png(path, np.ones((3, 4, 3)))
    assert matplotlib.image.imread(path).shape[:2] == (3, 4)
    with pytest.raises(ValueError, match="does not exist"):
        write_png(tmp_path / "missing" / "out.png", np.zeros((2, 2, 3)))


def test_atomic_write_leaves_old_file_on_error(tmp_path):
    path = tmp_path / "keep.png"
    path.write_bytes(b"old")

    def fail(f):
        f.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(path, fail)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test_comparison_png(tmp_path):
    a = np.zeros((4, 6, 3))
    b = np.ones((4, 6, 3)) * [1.0, 0.0, 0.0]
    path = tmp_path / "cmp.png"
    write_comparison_png(path, {"truth": a, "ours": b})
    img = matplotlib.image.imread(path)
    assert img.ndim == 3 and img.shape[1] > img.shape[0]
    # The red panel is in there.
    red = (img[..., 0] > 0.9) & (img[..., 1] < 0.1) & (img[..., 2] < 0.1)
    assert red.sum() > 100
    assert [p.name for p in tmp_path.iterdir()] == ["cmp.png"]


# --- cube files -----------------------------------------------------------------------


def test_cube_file_round_trip(tmp_path):
    cube = np.random.default_rng(2).random((3, 4, 72))
    path = tmp_path / "cube.npz"
    save_cube(path, cube, CENTRES, labels=np.arange(12).reshape(3, 4))
    out = load_cube(path)
    assert out["cube"].dtype == np.float32
    np.testing.assert_allclose(out["cube"], cube, rtol=1e-6)
    np.testing.assert_array_equal(out["wavelengths_nm"], CENTRES)
    np.testing.assert_array_equal(out["labels"], np.arange(12).reshape(3, 4))


@pytest.mark.parametrize(
    "arrays, match",
    [
        ({"cube": np.zeros((2, 2, 3))}, "lacks"),
        (
            {"cube": np.zeros((2, 3)), "wavelengths_nm": np.arange(3.0)},
            "does not match",
        ),
        (
            {"cube": np.zeros((2, 2, 3)), "wavelengths_nm": np.arange(4.0)},
            "does not match",
        ),
        (
            {"cube": np.zeros((2, 2, 3), int), "wavelengths_nm": np.arange(3.0)},
            "floats",
        ),
    ],
)
def test_bad_cube_files(tmp_path, arrays, match):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(ValueError, match=match):
        load_cube(path)


def test_unreadable_cube_files(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        load_cube(tmp_path / "absent.npz")
    path = tmp_path / "junk.npz"
    path.write_bytes(b"junk")
    with pytest.raises(ValueError, match="not a readable"):
        load_cube(path)
    with pytest.raises(ValueError, match="does not match"):
        save_cube(tmp_path / "c.npz", np.zeros((2, 2, 3)), CENTRES)
