"""Spectral grids, band integration, resampling, default D(λ) and E(λ)."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import scipy.integrate
import scipy.interpolate

from evhsi_jax._base._spectra import band_integrate_matrix
from evhsi_jax.forward import (
    SpectralGrid,
    band_integrate,
    default_camera_response,
    default_lamp_spectrum,
    resample,
)


def dense_bin_means(wl, values, edges, per_nm=2000):
    """Bin means of the piecewise-linear interpolant (held flat past the ends), by
    adaptive quadrature over each bin with the sample points as break points."""
    f = scipy.interpolate.interp1d(
        wl, values, bounds_error=False, fill_value=(values[0], values[-1])
    )
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        pts = wl[(wl > lo) & (wl < hi)]
        val, _ = scipy.integrate.quad(
            f, lo, hi, points=pts if pts.size else None, limit=500, epsabs=1e-13
        )
        out.append(val / (hi - lo))
    return np.array(out)


@pytest.mark.parametrize(
    "channels, start, stop, fine_step, sub",
    [
        (72, 400.0, 760.0, 1.0, 5),
        (36, 400.0, 760.0, 1.0, 10),
        (10, 450.0, 650.0, 3.0, 7),  # 20 nm channels split into ceil(20/3) = 7
        (4, 500.0, 520.0, 10.0, 1),
    ],
)
def test_grid_edges_centres(channels, start, stop, fine_step, sub):
    g = SpectralGrid(channels, start, stop, fine_step)
    width = (stop - start) / channels
    assert g.sub == sub
    np.testing.assert_allclose(g.edges_nm, start + width * np.arange(channels + 1))
    np.testing.assert_allclose(
        g.centres_nm, start + width * (np.arange(channels) + 0.5)
    )
    fw = width / sub
    np.testing.assert_allclose(
        g.fine_edges_nm, start + fw * np.arange(channels * sub + 1), atol=1e-9
    )
    np.testing.assert_allclose(
        g.fine_centres_nm, start + fw * (np.arange(channels * sub) + 0.5), atol=1e-9
    )
    # fine_to_channels averages each channel's sub-bins.
    fine = np.random.default_rng(0).random((3, channels * sub))
    np.testing.assert_allclose(
        g.fine_to_channels(fine), fine.reshape(3, channels, sub).mean(-1)
    )


def test_default_grid_is_paper_grid():
    g = SpectralGrid()
    np.testing.assert_allclose(g.centres_nm, np.arange(402.5, 760.0, 5.0))
    assert g.channels == 72 and g.sub == 5


def test_grid_equality_and_hash():
    assert SpectralGrid() == SpectralGrid(72, 400.0, 760.0, 1.0)
    assert hash(SpectralGrid()) == hash(SpectralGrid(72, 400.0, 760.0, 1.0))
    assert SpectralGrid() != SpectralGrid(36)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(channels=1), "channels"),
        (dict(channels=0), "channels"),
        (dict(start_nm=500.0, stop_nm=400.0), "channel_start_nm"),
        (dict(start_nm=float("nan")), "finite"),
        (dict(fine_step_nm=0.0), "fine_step_nm"),
    ],
)
def test_grid_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SpectralGrid(**kwargs)


@pytest.mark.parametrize(
    "wl, edges",
    [
        # Irregular samples, bins that cut between them.
        (
            np.sort(np.random.default_rng(1).uniform(380, 780, 40)),
            np.linspace(400, 760, 13),
        ),
        # Bins finer than the samples (one sample spacing holds several bins).
        (np.arange(380.0, 781.0, 10.0), np.linspace(400, 430, 31)),
        # Bin edges exactly on sample points.
        (np.arange(380.0, 781.0, 5.0), np.arange(400.0, 761.0, 5.0)),
    ],
)
def test_band_integrate_exact_for_piecewise_linear(wl, edges):
    if wl[0] > edges[0] or wl[-1] < edges[-1]:  # the random grid may not quite cover
        wl = np.concatenate([[edges[0] - 1.0], wl, [edges[-1] + 1.0]])
    vals = np.random.default_rng(2).random((2, wl.size))
    got = band_integrate(wl, vals, edges)
    want = np.stack([dense_bin_means(wl, v, edges) for v in vals])
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    # The matrix form is the same operator.
    np.testing.assert_allclose(vals @ band_integrate_matrix(wl, edges), got, atol=1e-12)


def test_band_integrate_held_flat_past_the_ends():
    """Half a sample of slack at each end: the value is held constant there."""
    wl = np.arange(402.5, 760.0, 5.0)  # centres: 400 and 760 are 2.5 nm outside
    vals = np.linspace(0.0, 1.0, wl.size)
    got = band_integrate(wl, vals, [400.0, 405.0, 755.0, 760.0])
    want = dense_bin_means(wl, vals, np.array([400.0, 405.0, 755.0, 760.0]))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    # First bin: 0 on [400, 402.5], then a ramp from 0 to 0.5/71 at 405 nm.
    np.testing.assert_allclose(got[0], (0.5 * 2.5 * 0.5 / 71) / 5.0)


def test_band_integrate_constant_and_linear():
    wl = np.array([300.0, 900.0])
    edges = np.array([400.0, 410.0, 500.0])
    np.testing.assert_allclose(band_integrate(wl, [0.7, 0.7], edges), [0.7, 0.7])
    # f(λ) = λ: the bin mean is the bin centre.
    np.testing.assert_allclose(band_integrate(wl, wl, edges), [405.0, 455.0])


@pytest.mark.parametrize(
    "wl, values, edges, match",
    [
        ([400.0, 500.0, 600.0], [1.0, 2.0], [400.0, 600.0], "samples"),
        ([400.0, 390.0, 600.0], [1.0, 2.0, 3.0], [400.0, 600.0], "increasing"),
        ([400.0, 500.0, 600.0], [1.0, np.nan, 3.0], [400.0, 600.0], "NaN"),
        ([450.0, 500.0, 600.0], [1.0, 2.0, 3.0], [400.0, 600.0], "span"),
        ([400.0, 500.0, 600.0], [1.0, 2.0, 3.0], [500.0, 450.0], "edges"),
    ],
)
def test_band_integrate_rejects_bad_input(wl, values, edges, match):
    with pytest.raises(ValueError, match=match):
        band_integrate(wl, values, edges)


def test_resample_matches_scipy():
    rng = np.random.default_rng(3)
    wl = np.sort(rng.uniform(380, 780, 30))
    wl[0], wl[-1] = 380.0, 780.0
    vals = rng.random((2, 3, wl.size))
    new = np.linspace(400, 760, 97)
    want = scipy.interpolate.interp1d(wl, vals, axis=-1)(new)
    got = resample(wl, vals, new)
    assert got.shape == (2, 3, 97)
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_resample_requires_cover():
    with pytest.raises(ValueError, match="span"):
        resample([450.0, 460.0], [1.0, 2.0], [400.0, 455.0])


def test_default_camera_response():
    wl = np.linspace(400, 760, 361)
    d = default_camera_response(wl)
    assert np.all(d > 0)
    np.testing.assert_allclose(d.max(), 1.0)
    assert wl[np.argmax(d)] == 600.0
    np.testing.assert_allclose(d, np.exp(-0.5 * ((wl - 600.0) / 160.0) ** 2))
    # The values its docstring promises.
    np.testing.assert_allclose(
        default_camera_response([400.0, 760.0]), [0.46, 0.61], atol=0.01
    )


def test_default_lamp_is_kinoton_peak_one():
    wl = SpectralGrid().fine_centres_nm
    e = default_lamp_spectrum(wl)
    assert np.all(e > 0)
    np.testing.assert_allclose(e.max(), 1.0)
    sd = colour.SDS_LIGHT_SOURCES["Kinoton 75P"]
    ref = np.interp(wl, sd.wavelengths, sd.values)
    np.testing.assert_allclose(e, ref / ref.max(), rtol=1e-12)


def test_stored_reference_spectra_equal_colour_science():
    """The lamp and ColorChecker spectra kept as package data (so that a `Rig()` does
    not import colour-science, ~2 s) are colour-science's own values."""
    from evhsi_jax._base._reference_spectra import from_colour, reference_spectra

    stored, live = reference_spectra(), from_colour()
    assert stored.keys() == live.keys()
    for k in live:
        np.testing.assert_array_equal(stored[k], live[k], err_msg=k)
