"""Scenes: built-ins against colour-science's data, metamers, files, validation."""

from __future__ import annotations

import warnings

import colour
import numpy as np
import pytest

from evhsi_jax import Rig, Scene, load_scene
from evhsi_jax._model._scenes import parse_size
from evhsi_jax.forward import BUILTIN_SCENES

CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]


def xyz(wl, values, illuminant="D65"):
    """CIE 1931 XYZ (Y of a perfect white = 1) by colour-science (ASTM E308)."""
    sd = colour.SpectralDistribution(dict(zip(wl, values)))
    with warnings.catch_warnings():  # "aligning the illuminant to the CMFs' shape"
        warnings.simplefilter("ignore", colour.utilities.ColourRuntimeWarning)
        return colour.sd_to_XYZ(sd, CMFS, colour.SDS_ILLUMINANTS[illuminant]) / 100.0


def ohta():
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    names = list(sds)
    return names, np.stack([np.asarray(sds[k].values) for k in names]), sds[names[0]]


@pytest.mark.parametrize("name", BUILTIN_SCENES)
@pytest.mark.parametrize("size", [None, (8, 12), (4, 22)])
def test_builtin_scene_is_valid(name, size):
    scene = load_scene(name, size)
    if size is not None:
        assert (scene.height, scene.width) == size
    assert scene.palette.min() >= 0 and scene.palette.max() <= 1
    assert scene.wavelengths_nm[0] <= 400 and scene.wavelengths_nm[-1] >= 760
    assert scene.labels.min() >= 0 and scene.labels.max() < len(scene.palette)
    assert len(scene.names) == len(scene.palette)
    # Every material of the scene is visible at these sizes.
    if size != (4, 22):  # 4 rows cannot show the gray chart's 6 stripes
        assert np.unique(scene.labels).size == len(scene.palette)


def test_default_size():
    scene = load_scene("colorchecker")
    assert (scene.height, scene.width) == (96, 144)


def test_colorchecker_is_ohta_in_4x6():
    names, values, first = ohta()
    scene = load_scene("colorchecker", (8, 12))
    np.testing.assert_allclose(scene.wavelengths_nm, first.wavelengths)
    np.testing.assert_allclose(scene.palette, values)
    assert list(scene.names) == names
    # Patch k covers rows 2(k // 6)..+1 and columns 2(k % 6)..+1.
    want = np.kron(np.arange(24).reshape(4, 6), np.ones((2, 2), int))
    np.testing.assert_array_equal(scene.labels, want)


def test_gray_chart_has_six_neutral_stripes():
    names, values, _ = ohta()
    scene = load_scene("gray-chart", (12, 5))
    np.testing.assert_allclose(scene.palette, values[18:24])
    assert all(n.startswith(("white", "neutral", "black")) for n in scene.names)
    np.testing.assert_array_equal(
        scene.labels, np.repeat(np.arange(6), 2)[:, None] * np.ones(5, int)
    )
    # Neutral: flat within a few percent over 420-740 nm, ordered white → black.
    wl = scene.wavelengths_nm
    band = (wl >= 420) & (wl <= 740)
    means = scene.palette[:, band].mean(1)
    assert np.all(np.diff(means) < 0)
    spread = scene.palette[:, band].std(1) / means
    assert np.all(spread < 0.1)


def test_rainbow_structure():
    w = 9
    scene = load_scene("rainbow", (6, w))
    wl = scene.wavelengths_nm
    centres = 420.0 + 320.0 * np.arange(w) / (w - 1)
    peak, step, notch = (scene.palette[scene.labels[r]] for r in (0, 2, 4))
    for x, c in enumerate(centres):
        assert wl[np.argmax(peak[x])] == pytest.approx(c, abs=0.5)
        assert wl[np.argmin(notch[x])] == pytest.approx(c, abs=0.5)
        # 10 nm FWHM: half of the 0.9 peak above the 0.03 floor at ±5 nm.
        np.testing.assert_allclose(
            np.interp(c + 5.0, wl, peak[x]), 0.03 + 0.45, atol=1e-3
        )
        assert np.interp(c - 1.0, wl, step[x]) == pytest.approx(0.05)
        assert np.interp(c + 1.0, wl, step[x]) == pytest.approx(0.85)


def test_tcs_training_set():
    from colour.quality.datasets.tcs import SDS_TCS

    scene = load_scene("tcs", (4, 11))
    assert len(scene.palette) == 44
    np.testing.assert_array_equal(scene.labels, np.arange(44).reshape(4, 11))
    sd = SDS_TCS["CIE 1995"]["TCS01"]
    np.testing.assert_allclose(
        scene.palette[0],
        np.clip(np.interp(scene.wavelengths_nm, sd.wavelengths, sd.values), 0, 1),
    )
    # Disjoint from the ColorChecker used for evaluation.
    _, cc, _ = ohta()
    cc_on = np.stack(
        [np.interp(scene.wavelengths_nm, ohta()[2].wavelengths, v) for v in cc]
    )
    dist = np.abs(scene.palette[:, None, :] - cc_on[None]).max(-1)
    assert dist.min() > 0.01


def test_metamers_match_in_colour_not_in_spectrum():
    scene = load_scene("metamers", (2, 4))
    wl = scene.wavelengths_nm
    base, twin = scene.palette[:4], scene.palette[4:]
    np.testing.assert_array_equal(scene.labels, np.arange(8).reshape(2, 4))
    for a, b in zip(base, twin):
        xyz_a, xyz_b = xyz(wl, a), xyz(wl, b)
        np.testing.assert_allclose(xyz_a, xyz_b, atol=3e-4)
        np.testing.assert_allclose(
            colour.XYZ_to_sRGB(xyz_a), colour.XYZ_to_sRGB(xyz_b), atol=1e-3
        )
        assert np.abs(a - b).max() > 0.04  # different spectra
        # ... that a different light tells apart.
        assert np.abs(xyz(wl, a, "A") - xyz(wl, b, "A")).max() > 1e-3
    # The base patches are the ColorChecker's.
    names, values, _ = ohta()
    for k, n in enumerate(scene.names[:4]):
        np.testing.assert_allclose(base[k], values[names.index(n)])
    # Rendered through the library's channel pipeline they stay metamers.
    from evhsi_jax import cube_to_srgb

    truth = scene.truth_cube(Rig().grid)
    rgb = cube_to_srgb(truth, Rig().wavelengths_nm)
    np.testing.assert_allclose(rgb[0], rgb[1], atol=0.01)


def test_truth_cube_is_channel_average():
    scene = load_scene("colorchecker", (4, 6))
    rig = Rig()
    cube = scene.truth_cube(rig.grid)
    assert cube.shape == (4, 6, 72) and cube.dtype == np.float32
    # Channel means by dense midpoint integration of the linear interpolant.
    e = rig.grid.edges_nm
    frac = (np.arange(200) + 0.5) / 200
    lam = (e[:-1, None] + 5.0 * frac).ravel()
    want = (
        np.interp(lam, scene.wavelengths_nm, scene.palette[7]).reshape(72, 200).mean(1)
    )
    np.testing.assert_allclose(cube[1, 1], want, atol=1e-5)


def test_from_cube_shares_identical_spectra():
    rng = np.random.default_rng(0)
    pal = rng.random((3, 5))
    labels = rng.integers(0, 3, (4, 7))
    cube = pal[labels]
    scene = Scene.from_cube(cube, np.linspace(400, 760, 5))
    assert len(scene.palette) == 3
    np.testing.assert_array_equal(scene.reflectance(), cube)


def test_scene_file_round_trip(tmp_path):
    scene = load_scene("metamers", (6, 8))
    path = tmp_path / "scene.npz"
    scene.save_npz(path)
    with np.load(path) as data:
        assert set(data.files) == {"reflectance", "wavelengths_nm"}
        assert data["reflectance"].shape == (6, 8, scene.wavelengths_nm.size)
    back = load_scene(path)
    np.testing.assert_allclose(back.reflectance(), scene.reflectance(), atol=1e-7)
    np.testing.assert_array_equal(back.wavelengths_nm, scene.wavelengths_nm)
    assert len(back.palette) == len(scene.palette)
    assert load_scene(str(path), (6, 8)).height == 6


def test_scene_file_any_grid(tmp_path):
    """A user's cube on its own (coarse, irregular) grid loads as is."""
    wl = np.array([390.0, 450.0, 520.0, 610.0, 700.0, 770.0])
    refl = np.random.default_rng(1).random((3, 4, 6))
    path = tmp_path / "mine.npz"
    np.savez(path, reflectance=refl, wavelengths_nm=wl)
    scene = load_scene(path)
    np.testing.assert_allclose(scene.reflectance(), refl)


def _write(path, **arrays):
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda p: p.with_suffix(".txt"), "unknown scene"),
        (lambda p: p, "not found"),
        (lambda p: (p.write_bytes(b"not a zip file"), p)[1], "not a readable"),
        (lambda p: _write(p, reflectance=np.zeros((2, 2, 3))), "lacks keys"),
        (
            lambda p: _write(
                p, reflectance=np.zeros((2, 3)), wavelengths_nm=[400, 500, 600]
            ),
            "must be \\(H, W, L\\)",
        ),
        (
            lambda p: _write(
                p, reflectance=np.full((2, 2, 3), 1.5), wavelengths_nm=[400, 500, 600]
            ),
            "\\[0, 1\\]",
        ),
        (
            lambda p: _write(
                p, reflectance=np.zeros((2, 2, 3)), wavelengths_nm=[400, 600, 500]
            ),
            "increasing",
        ),
        (
            lambda p: _write(
                p,
                reflectance=np.full((2, 2, 3), np.nan),
                wavelengths_nm=[400, 500, 600],
            ),
            "NaN",
        ),
        (
            lambda p: _write(
                p, reflectance=np.zeros((2, 2, 3)), wavelengths_nm=[400, 500]
            ),
            "does not match",
        ),
        (
            lambda p: _write(
                p,
                reflectance=np.array([None], dtype=object),
                wavelengths_nm=[400, 500],
            ),
            "not a readable",
        ),
    ],
)
def test_bad_scene_files(tmp_path, make, match):
    path = make(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match=match):
        load_scene(path)


def test_file_size_cannot_be_changed(tmp_path):
    path = tmp_path / "s.npz"
    load_scene("gray-chart", (6, 4)).save_npz(path)
    with pytest.raises(ValueError, match="cannot resize"):
        load_scene(path, (12, 8))


def test_unknown_name():
    with pytest.raises(ValueError, match="colorchecker"):
        load_scene("mondrian")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (
            dict(palette=np.zeros((2, 3)), wavelengths_nm=np.arange(4.0)),
            "does not match",
        ),
        (dict(palette=np.full((1, 2), -0.1)), "\\[0, 1\\]"),
        (dict(palette=np.full((1, 2), np.inf)), "NaN or Inf"),
        (dict(wavelengths_nm=np.array([500.0, 400.0])), "increasing"),
        (dict(labels=np.zeros((2, 2), float)), "integer"),
        (dict(labels=np.zeros(3, int)), "2-D"),
        (dict(labels=np.full((2, 2), 1)), "outside the palette"),
        (dict(labels=np.full((2, 2), -1)), "outside the palette"),
    ],
)
def test_scene_validation(kwargs, match):
    args = dict(
        palette=np.full((1, 2), 0.5),
        wavelengths_nm=np.array([400.0, 700.0]),
        labels=np.zeros((2, 2), int),
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        Scene(**args)


@pytest.mark.parametrize(
    "text, want",
    [("720x1280", (720, 1280)), ("4X6", (4, 6)), (None, None)],
)
def test_parse_size(text, want):
    assert parse_size(text) == want


@pytest.mark.parametrize("text", ["720", "axb", "0x5", "4x6x2", "9000x10"])
def test_parse_size_errors(text):
    with pytest.raises(ValueError, match="size"):
        parse_size(text)
