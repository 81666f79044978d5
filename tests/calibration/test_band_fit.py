"""The calibration fits the band profile: a gray chart sees the band's shape where the
band enters and leaves the channel range (README, Calibration, "The band profile")."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._model._illumination import (
    TABLE_STEP_NM,
    _profile_overlap,
    sampled_profile_overlap,
    sampled_profile_product,
)


def _shouldered_band(fwhm: float, shoulder: float = 0.35) -> dict:
    """A band outside every parametric family the fit knows: a Gaussian with a
    shoulder on its red side (35 % of the peak, 0.6 FWHM out; 0: the Gaussian)."""
    off = np.linspace(-3 * fwhm, 3 * fwhm, 161)
    s = fwhm / 2.3548
    val = np.exp(-(off**2) / (2 * s**2)) + shoulder * np.exp(
        -((off - 0.6 * fwhm) ** 2) / (2 * (0.7 * s) ** 2)
    )
    return {"offset_nm": off.tolist(), "values": (val / val.max()).tolist()}


def test_the_traced_overlap_is_the_sampled_profiles():
    prof = _shouldered_band(17.5)
    off, val = np.asarray(prof["offset_nm"]), np.asarray(prof["values"])
    with jax.enable_x64(True):
        edges = np.arange(390.0, 771.0, 1.0)
        centres = jnp.asarray(300.0 + TABLE_STEP_NM * np.arange(4000))
        want = _profile_overlap((tuple(off), tuple(val)), jnp.asarray(edges), centres)
        got = sampled_profile_overlap(off, jnp.asarray(val), edges, 300.0, TABLE_STEP_NM, 4000)
        np.testing.assert_allclose(got, want, atol=1e-12 * float(jnp.max(want)))


def test_with_band_profile_validates_like_a_rig_file():
    rig = ev.Rig().with_band_profile(_shouldered_band(17.5))
    assert rig.band_profile is not None and max(rig.band_profile[1]) == 1.0
    assert ev.Rig().with_band_profile("skewed").band_profile is not None
    assert rig.with_band_profile(None).band_profile is None
    with pytest.raises(ValueError, match="band_profile"):
        ev.Rig().with_band_profile({"offset_nm": [0, 1, 2], "values": [0, -1, 0]})


def _watch_strip(mp) -> list:
    """Watch the wide-chart path through `mp` (a MonkeyPatch): each calibration of
    the strip appends the whole chart's width and whether the band was fitted there."""
    from evhsi_jax._calibrate import _fit

    seen, inner = [], _fit._band_from_strip

    def strip(events, *a, **kw):
        rig, fitted = inner(events, *a, **kw)
        seen.extend([events.width, fitted])
        return rig, fitted

    mp.setattr(_fit, "_band_from_strip", strip)
    return seen


@pytest.fixture(scope="module")
def shouldered():
    """A 24x32 gray chart of 4 sweeps and a held-out TCS sweep, from a sensor whose
    band has a shoulder. Calibrated from the default rig, which has a Gaussian band:
    the band fitted (the default when the initial rig gives no profile), here on a
    16-column strip first (`BAND_CROP_COLUMNS`, 32 by default, on charts wider than
    `BAND_DIRECT_COLUMNS`, 64: the path of a wide sensor); and from a rig that gives
    the Gaussian as a sampled profile, which the calibration keeps by default (a
    profile measured with a spectrometer)."""
    from evhsi_jax._calibrate import _fit

    true = ev.Rig.from_dict({"band_profile": _shouldered_band(17.5)})
    key = jr.key(7)
    chart = ev.load_scene("gray-chart", (24, 32))
    gray = ev.simulate(chart, true, sweeps=4, key=key)
    scene = ev.load_scene("tcs", (24, 32))
    held_out = ev.simulate(scene, true, sweeps=1, key=key)
    truth = scene.truth_cube(true.grid)
    with pytest.MonkeyPatch.context() as m:  # (not verbose: the stored programs run)
        m.setattr(_fit, "BAND_DIRECT_COLUMNS", 16)
        m.setattr(_fit, "BAND_CROP_COLUMNS", 16)
        strips = _watch_strip(m)
        fitted = ev.calibrate(gray, chart, ev.Rig())
    given = ev.Rig.from_dict({"band_profile": _shouldered_band(17.5, shoulder=0.0)})
    kept = ev.calibrate(gray, chart, given)
    return true, held_out, truth, fitted, kept, given, strips


def test_a_shouldered_band_is_fitted_from_a_gray_chart(shouldered):
    true, held_out, truth, fitted, kept, _, strips = shouldered
    assert strips == [32, True]  # fitted on the middle 16 columns first
    assert fitted.calibration.report["band"] == "profile fitted"
    # The Gaussian leaves a misfit the fitted band does not (noise-free sensor).
    assert fitted.rms_residual < 0.01 < kept.rms_residual
    # The profile up to a shift (τx absorbs a common shift of the band).
    off, val = (np.asarray(v) for v in fitted.rig.band_profile)
    t_off, t_val = (np.asarray(v) for v in true.band_profile)
    grid = np.linspace(-40.0, 40.0, 801)
    got = np.interp(grid, off, val)
    err = min(
        np.abs(got - np.interp(grid - shift, t_off, t_val)).max()
        for shift in np.arange(-8.0, 8.01, 0.1)
    )
    assert err < 0.1
    # What it is for: the held-out scene.
    psnr_fit = ev.evaluate(ev.reconstruct(held_out, fitted.calibration), truth)["psnr_db"]
    psnr_kept = ev.evaluate(ev.reconstruct(held_out, kept.calibration), truth)["psnr_db"]
    assert psnr_fit > 33.0 and psnr_fit > psnr_kept + 8.0


def test_a_given_band_profile_is_kept_by_default(shouldered):
    *_, kept, given, _ = shouldered
    assert kept.rig.band_profile == given.band_profile
    assert kept.calibration.report["band"] == "kept from the initial rig"


@pytest.mark.parametrize("channels", [72, 71], ids=["on the grid", "off the grid"])
def test_the_fits_gathered_overlap_table_is_the_interpolated_one(channels):
    """`sampled_profile_overlap` gathers the table from the profile's cumulative
    integral at its distinct offsets when the fine edges lie on the table's grid of
    λc (the default rig), and falls back to one interpolation per entry when they do
    not; either way the table of the fit's band is that of the sampled profile."""
    from evhsi_jax._calibrate import _fit
    from evhsi_jax._model import band_overlap

    with jax.enable_x64(True):
        rig = ev.Rig(channels=channels).astype(jnp.float64)
        ov = band_overlap(rig)
        k = (np.asarray(rig.grid.fine_edges_nm) - ov.lo_nm) / ov.step_nm
        assert np.allclose(k, np.round(k), atol=1e-6) == (channels == 72)
        band = _fit._band_start(rig, jnp.float64)
        theta = 0.1 * jnp.sin(jnp.arange(_fit.BAND_KNOTS, dtype=float))
        vals = _fit._band_values(theta, band)
        n = ov.values.shape[0]
        centres = ov.lo_nm + ov.step_nm * jnp.arange(n, dtype=jnp.float64)
        prof = (tuple(np.asarray(band[0])), tuple(np.asarray(vals)))
        want = _profile_overlap(prof, jnp.asarray(rig.grid.fine_edges_nm), centres)
        got = sampled_profile_overlap(
            band[0], vals, rig.grid.fine_edges_nm, ov.lo_nm, ov.step_nm, n
        )
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * float(jnp.max(want)))


@pytest.mark.parametrize(
    "edges, n",
    [
        (np.arange(390.0, 771.0, 1.0), 4000),  # on the grid, 10 steps apart
        (np.arange(390.0, 771.0, 1.0), 4003),  # n not a multiple of the spacing
        (np.arange(390.0, 771.0, 0.5), 4000),  # 5 steps apart
        (np.arange(390.05, 771.0, 1.0), 4000),  # off the grid: the table's product
        (np.concatenate([[388.5], np.arange(390.0, 771.0, 1.0)]), 4000),  # uneven
    ],
    ids=["1 nm", "uneven n", "0.5 nm", "off the grid", "uneven edges"],
)
def test_the_fits_product_is_the_table_times_the_weights(edges, n):
    """`sampled_profile_product` (the band fit's traces, by convolution, without the
    table) equals the sampled profile's overlap table times the weights, and so do
    its derivatives along the profile's samples."""
    prof = _shouldered_band(17.5)
    off, val = np.asarray(prof["offset_nm"]), np.asarray(prof["values"])
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        w = jnp.asarray(rng.random((edges.size - 1, 3)))
        v = jnp.asarray(val)

        def table(v):
            return sampled_profile_overlap(off, v, edges, 300.0, TABLE_STEP_NM, n) @ w

        def product(v):
            return sampled_profile_product(off, v, edges, 300.0, TABLE_STEP_NM, n, w)

        want, got = table(v), product(v)
        assert got.shape == (n, 3)
        scale = float(jnp.max(jnp.abs(want)))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * scale)
        dv = jnp.asarray(rng.standard_normal(val.size))
        d_want = jax.jvp(table, (v,), (dv,))[1]
        d_got = jax.jvp(product, (v,), (dv,))[1]
        np.testing.assert_allclose(
            d_got, d_want, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(d_want)))
        )


@pytest.fixture(scope="module")
def small_gray():
    chart = ev.load_scene("gray-chart", (12, 16))
    return chart, ev.simulate(chart, ev.Rig(), sweeps=4, key=jr.key(3))


@pytest.mark.slow  # ~50-80 s of compilation with an empty cache: `make bench`
def test_a_band_fit_that_does_not_converge_keeps_the_band(small_gray, monkeypatch):
    """When the band's stage does not converge (a capture that does not determine
    the shape: 15 µs of timestamp jitter in the realism study), the stage runs again
    with the band kept, and the report says so. Non-convergence is forced here (the
    solver's answer replaced), through the wide-chart path: the strip's own fit
    gives up on the band that way, and the whole chart keeps it. (Not verbose: the
    stored programs run, and the whole chart's are those of the fit with the band
    kept, compiled once.)"""
    from evhsi_jax._calibrate import _fit

    chart, gray = small_gray
    call = _fit.call_exported

    def band_never_converges(name, fn, args, *rest, **kw):
        out = call(name, fn, args, *rest, **kw)
        fit = args[4] if name == "calibrate_lm" else None
        if fit is not None and fit.band is not None and float(fit.band_gate) == 1.0:
            return out[0], out[1], jnp.asarray(False)
        return out

    monkeypatch.setattr(_fit, "BAND_DIRECT_COLUMNS", 8)
    monkeypatch.setattr(_fit, "BAND_CROP_COLUMNS", 8)
    kept = ev.calibrate(gray, chart, ev.Rig(), fit_band=False)
    monkeypatch.setattr(_fit, "call_exported", band_never_converges)
    strips = _watch_strip(monkeypatch)
    res = ev.calibrate(gray, chart, ev.Rig())
    assert strips == [16, False]  # the strip's band fit gave up: the band kept
    assert res.converged and not res.band_fitted and res.band_unresolved
    assert res.rig.band_profile is None
    report = res.calibration.report["band"]
    assert report == "kept from the initial rig (its fit did not converge)"
    for k in ("threshold_on", "threshold_off", "beta_nm_per_rad", "baseline_rel"):
        a, b = float(getattr(res.rig, k)), float(getattr(kept.rig, k))
        assert a == pytest.approx(b, rel=1e-4), k
    np.testing.assert_allclose(
        res.rig.column_offsets_us, kept.rig.column_offsets_us, rtol=0, atol=0.05
    )
