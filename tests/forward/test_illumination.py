"""The sweeping rainbow: band table, lookup, per-column time tables, gradients."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

from evhsi_jax import Rig
from evhsi_jax._model._illumination import TABLE_STEP_NM, table_range_nm
from evhsi_jax.forward import (
    band_table,
    column_time_table,
    fwhm_to_sigma,
    lookup,
    sweep_times_us,
)


def raw_rows(rig, centres_nm, fwhm_nm, points_per_bin=400):
    """D·E·∫ Gaussian over each fine sub-bin, by a dense trapezoid rule (float64)."""
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    edges = rig.grid.fine_edges_nm
    frac = np.linspace(0.0, 1.0, points_per_bin + 1)
    lam = edges[:-1, None] + np.diff(edges)[:, None] * frac[None, :]  # (F, P)
    g = np.exp(
        -0.5 * ((lam[None] - np.asarray(centres_nm)[:, None, None]) / sigma) ** 2
    )
    integral = np.trapezoid(g, lam[None], axis=-1)  # (n, F)
    weight = np.asarray(rig.camera_response, np.float64) * np.asarray(
        rig.lamp, np.float64
    )
    return integral * weight


def erf_rows(rig, centres_nm, fwhm_nm):
    """The same rows in closed form (erf differences), for the normalising peak."""
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    edges = rig.grid.fine_edges_nm
    u = (edges[None, :] - np.asarray(centres_nm)[:, None]) / (sigma * np.sqrt(2.0))
    cdf = scipy.special.erf(u)
    weight = np.asarray(rig.camera_response, np.float64) * np.asarray(
        rig.lamp, np.float64
    )
    return sigma * np.sqrt(np.pi / 2) * np.diff(cdf, axis=1) * weight


@pytest.mark.parametrize("fwhm", [17.5, 5.0])
def test_table_rows_match_dense_integral(fwhm):
    with jax.enable_x64(True):
        rig = Rig(fwhm_nm=fwhm)
        table = band_table(rig)
        values = np.asarray(table.values)
    lo, hi = table_range_nm(rig)
    assert table.lo_nm == lo and table.step_nm == TABLE_STEP_NM
    n = values.shape[0]
    assert n == int(np.ceil((hi - lo) / TABLE_STEP_NM)) + 1
    nodes = lo + TABLE_STEP_NM * np.arange(n)
    gain = 1.0 / erf_rows(rig, nodes, fwhm).sum(1).max()
    rows = np.array([0, n // 5, n // 3, n // 2, n - 200, n - 1])
    want = raw_rows(rig, nodes[rows], fwhm) * gain
    np.testing.assert_allclose(values[rows], want, rtol=1e-5, atol=1e-12)


def test_table_peak_normalised_and_positive():
    table = band_table(Rig())
    v = np.asarray(table.values)
    assert np.all(v >= 0)
    np.testing.assert_allclose(v.sum(1).max(), 1.0, rtol=1e-6)
    # At the ends of the table the band misses the channels (< 1e-9 of the peak).
    assert v[0].sum() < 1e-9 and v[-1].sum() < 1e-9


def test_channel_table_sums_sub_bins():
    rig = Rig()
    fine = band_table(rig)
    ch = fine.channels(rig.grid.sub)
    assert ch.values.shape == (fine.values.shape[0], 72)
    np.testing.assert_allclose(
        np.asarray(ch.values),
        np.asarray(fine.values).reshape(-1, 72, 5).sum(-1),
        rtol=1e-6,
    )


def test_trimmed_table_keeps_each_band_above_its_own_fraction():
    """`trimmed` zeroes a band's entries below 1e-7 of that band's peak, keeps the
    rest as they were; the NumPy and the JAX route agree (the fused CPU kernel and the
    `cuda` backend take one each); a dim band (far from the lamp's peak) keeps its
    span: the rule is relative to each band, not to the table."""
    from evhsi_jax._model import BAND_TRIM, trim_rows

    rig = Rig()
    ch = band_table(rig).channels(rig.grid.sub)
    v = np.asarray(ch.values)
    t = np.asarray(ch.trimmed().values)
    peak = np.abs(v).max(axis=1, keepdims=True)
    keep = np.abs(v) > BAND_TRIM * peak
    np.testing.assert_array_equal(t, np.where(keep, v, 0.0))
    assert 0 < keep.sum() < (v != 0).sum()  # something was cut, most was not
    np.testing.assert_array_equal(trim_rows(v.astype(np.float64)), t.astype(np.float64))
    lit = peak[:, 0] > 0
    width = keep.sum(axis=1)[lit]
    assert 12 <= np.median(width) <= 20  # the paper's 17.5 nm band on 5 nm channels
    # Bands centred at 550 and 710 nm (where the lamp and camera give ~3 % of the
    # peak) keep the same width (1e-7 of the table's peak would cut the dim one to 15).
    bright, dim = (int(round((c - ch.lo_nm) / ch.step_nm)) for c in (550.0, 710.0))
    assert peak[dim, 0] < 0.05 * peak.max()
    assert keep[dim].sum() >= keep[bright].sum() - 1
    assert np.abs(v[~keep]).max() <= BAND_TRIM * np.abs(v).max()


def test_lookup_is_linear_interpolation_and_zero_outside():
    rig = Rig()
    table = band_table(rig).channels(rig.grid.sub)
    v = np.asarray(table.values, np.float64)
    n = v.shape[0]
    nodes = table.lo_nm + table.step_nm * np.arange(n)
    rng = np.random.default_rng(0)
    centres = np.concatenate(
        [rng.uniform(nodes[0], nodes[-1], 50), nodes[[0, 7, -1]], [450.05, 600.0]]
    )
    got = np.asarray(lookup(table, jnp.asarray(centres, jnp.float32)))
    want = np.stack([np.interp(centres, nodes, v[:, m]) for m in range(72)], -1)
    np.testing.assert_allclose(got, want, atol=2e-6)
    outside = jnp.asarray([nodes[0] - 0.01, nodes[-1] + 0.01, -1e4, 1e4], jnp.float32)
    np.testing.assert_array_equal(np.asarray(lookup(table, outside)), 0.0)


def test_lookup_any_shape():
    rig = Rig()
    table = band_table(rig)
    c = jnp.linspace(380.0, 700.0, 12).reshape(3, 4)
    out = lookup(table, c)
    assert out.shape == (3, 4, 360)
    np.testing.assert_array_equal(
        np.asarray(out[1, 2]), np.asarray(lookup(table, c[1, 2]))
    )


@pytest.mark.parametrize("order", [1, 3])
def test_lookup_tangents_are_the_jvps_of_lookup(order):
    """`lookup_tangents` (the table and its tangents read in one gather) against
    `jax.jvp` of `lookup` along each direction: tangents of the table's values and of
    the centres together, with centres at nodes, between them, near the ends and off
    the table (value and tangents 0 there)."""
    from evhsi_jax._model import BandTable, lookup_tangents

    with jax.enable_x64(True):
        table = band_table(Rig()).channels(Rig().grid.sub)
        values = jnp.asarray(table.values, jnp.float64)[:, :5]
        n = values.shape[0]
        nodes = table.lo_nm + table.step_nm * np.arange(n)
        rng = np.random.default_rng(1)
        centres = np.concatenate(
            [rng.uniform(nodes[0], nodes[-1], 38), nodes[[0, 1, 5, -2, -1]],
             [nodes[0] - 3.0, nodes[-1] + 0.2]]
        ).reshape(3, 3, 5)  # fmt: skip
        centres = jnp.asarray(centres)
        column = jnp.asarray(rng.integers(0, 5, centres.shape))
        t = 3
        d_values = jnp.asarray(rng.normal(size=(t,) + values.shape))
        d_centres = jnp.asarray(rng.normal(size=(t,) + centres.shape))

        def f(v, c):
            return lookup(BandTable(v, table.lo_nm, table.step_nm), c, order=order,
                          column=column)  # fmt: skip

        stacked = jnp.concatenate([values[..., None], jnp.moveaxis(d_values, 0, -1)], -1)
        got, d_got = lookup_tangents(
            BandTable(stacked, table.lo_nm, table.step_nm), centres, d_centres,
            column=column, order=order,
        )  # fmt: skip
        np.testing.assert_allclose(got, f(values, centres), rtol=1e-12, atol=1e-300)
        for i in range(t):
            want = jax.jvp(f, (values, centres), (d_values[i], d_centres[i]))[1]
            np.testing.assert_allclose(d_got[i], want, rtol=1e-12, atol=1e-14)
        assert not np.any(np.asarray(d_got)[:, -1, -1, -2:])  # off the table
    assert d_got.shape == (t,) + centres.shape
    with pytest.raises(ValueError, match="order"):
        lookup_tangents(BandTable(stacked, table.lo_nm, table.step_nm), centres,
                        d_centres, column=column, order=2)  # fmt: skip


def test_column_time_table_reads_band_centre():
    rig = Rig()
    table = band_table(rig)
    t = sweep_times_us(rig)
    tau = jnp.asarray(-1234.5)
    got = column_time_table(rig, table, t, tau)
    period = 1e6 / 30.0
    lam = 360.0 + 185.0 * np.pi * 30e-6 * (
        np.mod(np.asarray(t, np.float64), period) - 1234.5
    )
    want = lookup(table, jnp.asarray(lam, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-5)


def test_sweep_times():
    rig = Rig(samples_per_sweep=300, sweep_rate_hz=20.0)
    t = np.asarray(sweep_times_us(rig))
    np.testing.assert_allclose(t, np.arange(301) * 50000.0 / 300, rtol=1e-6)


def test_fwhm_to_sigma():
    s = fwhm_to_sigma(17.5)
    # Half maximum at ±FWHM/2.
    np.testing.assert_allclose(np.exp(-0.5 * (8.75 / s) ** 2), 0.5)


def test_jit_equals_eager():
    rig = Rig()
    eager = band_table(rig)
    jitted = eqx.filter_jit(lambda r: band_table(r, fwhm_bound_nm=17.5).values)(rig)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager.values), atol=1e-6)
    c = jnp.linspace(350.0, 800.0, 64)
    np.testing.assert_allclose(
        np.asarray(jax.jit(lookup)(eager, c)), np.asarray(lookup(eager, c)), atol=1e-7
    )


def test_vmap_lookup_equals_loop():
    rig = Rig()
    table = band_table(rig).channels(rig.grid.sub)
    c = jnp.linspace(380.0, 790.0, 40).reshape(8, 5)
    batched = jax.vmap(lookup, in_axes=(None, 0))(table, c)
    for i in range(8):
        np.testing.assert_array_equal(
            np.asarray(batched[i]), np.asarray(lookup(table, c[i]))
        )


def test_float32_float64_tables_agree():
    v32 = np.asarray(band_table(Rig()).values, np.float64)
    with jax.enable_x64(True):
        v64 = np.asarray(band_table(Rig()).values)
    np.testing.assert_allclose(v32, v64, atol=2e-6)
    # Relative accuracy in the band's tails too (no cancellation in float32).
    tail = v64 > 1e-20
    np.testing.assert_allclose(v32[tail], v64[tail], rtol=1e-3)


# --- gradients -----------------------------------------------------------------------

PARAMS = [
    "fwhm_nm",
    "beta_nm_per_rad",
    "column_offsets_us",
    "baseline_rel",
    "sweep_start_nm",
]


@pytest.fixture(scope="module")
def intensity_gradients():
    """Gradient and central differences of a weighted log-intensity sum, float64."""
    with jax.enable_x64(True):
        rig = Rig(column_offsets_us=[-900.0])
        fine = rig.grid.fine_centres_nm
        spectrum = jnp.asarray(0.2 + 0.7 * np.exp(-0.5 * ((fine - 560.0) / 50.0) ** 2))
        t = sweep_times_us(rig)
        w = jnp.sin(t / 3000.0)  # weights, so that a time shift changes the value

        @jax.jit
        def f(params):
            r = rig.with_leaves(**params)
            table = band_table(r, fwhm_bound_nm=25.0)
            a = column_time_table(r, table, t, r.column_offsets_us[0])
            inten = a @ spectrum + r.baseline_rel
            return jnp.sum(jnp.log(inten + r.log_eps) * w)

        p0 = {k: getattr(rig, k) for k in PARAMS}
        grad = jax.jit(jax.grad(f))(p0)
        out = {}
        for k in PARAMS:
            h = 1e-4 * max(1.0, float(jnp.max(jnp.abs(p0[k]))))
            fd = (float(f({**p0, k: p0[k] + h})) - float(f({**p0, k: p0[k] - h}))) / (
                2 * h
            )
            out[k] = (np.asarray(grad[k]), fd)
        return out


@pytest.mark.parametrize("name", PARAMS)
def test_intensity_gradients_match_finite_differences(intensity_gradients, name):
    grad, fd = intensity_gradients[name]
    assert np.all(np.isfinite(grad))
    assert abs(grad.sum()) > 1e-6  # the parameter matters
    np.testing.assert_allclose(grad.sum(), fd, rtol=2e-3)
