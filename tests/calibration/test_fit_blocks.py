"""The calibration's blocked Gauss–Newton system against a dense Jacobian.

`_fit_chart_float64` hands optimistix a reduced residual built from normal equations
accumulated over blocks of packed events; here they are checked against `jax.jacfwd`
of the whole residual vector (every event and the τx prior) on a small chart, with
blocks small enough that the chart's events fill several, each holding pixels of
several event counts.
"""

import jax
import jax.flatten_util
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._calibrate import _fit as F
from evhsi_jax._calibrate._chart import chart_data
from evhsi_jax._model import band_overlap


@pytest.fixture(scope="module")
def packed():
    """A 12×6 chart's events packed into blocks small enough that they fill several."""
    h, w = 12, 6
    truth = ev.Rig(threshold_on=0.17, photoreceptor_hz=20000.0)
    chart = ev.load_scene("gray-chart", (h, w))
    events = ev.simulate(chart, truth, sweeps=1, key=jr.key(5))
    with jax.enable_x64(True):
        rig = F._with_column_offsets(ev.Rig(photoreceptor_hz=20000.0), w).astype(
            jnp.float64
        )
        data = chart_data(events, chart, rig, rows_per_label=None)
        old = F.BLOCK_EVENTS
        F.BLOCK_EVENTS = 64  # several blocks
        try:
            blocks, layout = F._packed(data, jnp.float64)
        finally:
            F.BLOCK_EVENTS = old
    return rig, data, blocks, layout


@pytest.fixture(scope="module", params=[False, True], ids=["band kept", "band fitted"])
def system(request, packed):
    """(With the band fitted, the system holds its 17 knots and their prior too.)"""
    rig, data, blocks, layout = packed
    w = data.width
    with jax.enable_x64(True):
        band = F._band_start(rig, jnp.float64) if request.param else None
        fit = F._fit_data(rig, F._response_basis(rig, 2), blocks, data.spectra, None,
                          band_overlap(rig), band, jnp.ones((), jnp.float64),
                          True)  # fmt: skip
        key = jr.key(1)
        u = {  # away from the start, so every derivative is non-trivial
            "log_on": jnp.asarray(0.02),
            "log_off": jnp.asarray(-0.01),
            "log_beta": jnp.asarray(0.003),
            "log_c": jnp.asarray(0.05),
            "curv": jnp.asarray(0.4),
            "tau": 0.05 * jr.normal(key, (w,), jnp.float64),
            "resp": jnp.asarray([0.03, -0.02]),
        }
        if request.param:
            u["band"] = 0.1 * jr.normal(jr.key(2), (F.BAND_KNOTS,), jnp.float64)
        scale = jax.tree.map(lambda a: 1.5 + jnp.zeros_like(a), u)
        keep = np.ones(data.t_us.shape[0])
        keep[3] = 0.0  # one pixel dropped
        keep = layout.per_slot(keep, np.float64)  # (the fit's layout)
        yield u, scale, keep, fit, data, blocks, layout


@jax.jit
def _dense(u, scale, keep, fit, profile):
    """JᵀJ, Jᵀr and rᵀr of every residual (the events' and the priors'), from the
    dense `jax.jacfwd`. (`profile` an array, as in the fit: one program for both.)"""
    flat, unravel = jax.flatten_util.ravel_pytree(u)

    def all_residuals(uf):
        th = F._theta(uf, unravel, scale)
        res = F._fit_residuals(th, profile, keep, fit).reshape(-1)
        band = [F._band_prior(th["band"], fit.band)] if "band" in th else []
        return jnp.concatenate([res, F._prior_residuals(th, fit), *band])

    r, j = all_residuals(flat), jax.jacfwd(all_residuals)(flat)
    return j.T @ j, j.T @ r, r @ r


@jax.jit
def _system(u, scale, keep, fit, profile):
    return F._fit_system(u, (scale, (profile, keep, fit)))


@pytest.mark.parametrize("profile", [False, True])
def test_blocked_normal_equations_match_the_dense_jacobian(system, profile):
    u, scale, keep, fit, data, _, layout = system
    assert layout.shape[0] >= 4
    # Pixels of different event counts share blocks.
    lengths = np.bincount(layout.rows, minlength=layout.lists[0])
    block_of = layout.slot // layout.shape[1]
    first = np.searchsorted(layout.rows, np.arange(layout.lists[0]))
    per_block = [set(lengths[layout.rows[first][block_of[first] == b]]) for b in range(3)]
    assert all(len(c) >= 2 for c in per_block), per_block
    with jax.enable_x64(True):
        # jitted (op by op, a cold cache compiled every primitive on its own)
        profile = jnp.asarray(profile)  # (as in the fit: one program for both)
        h, b, ss = _system(u, scale, keep, fit, profile)
        h_ref, b_ref, ss_ref = _dense(u, scale, keep, fit, profile)
    np.testing.assert_allclose(h, h_ref, rtol=1e-9, atol=1e-9 * float(jnp.max(h_ref)))
    np.testing.assert_allclose(
        b, b_ref, rtol=1e-9, atol=1e-9 * float(jnp.max(abs(b_ref)))
    )
    np.testing.assert_allclose(ss, ss_ref, rtol=1e-12)


def test_jacobi_scale_by_differences_matches_the_derivatives(system):
    """`_jacobi_scale`'s forward differences of the residuals' program (one per
    global parameter, one with every τx moved at once) give the Jacobian's column
    norms — here from `jax.jacfwd`, one column per τx — to ~1e-6."""
    u, scale, keep, fit, data, _, layout = system
    with jax.enable_x64(True):
        theta = F._unscale(u, scale)
        res = jax.jit(lambda p: F._fit_residuals(p, jnp.asarray(False), keep, fit))
        got, ss = F._jacobi_scale(
            theta, lambda p: np.asarray(res(p)), layout.column, data.width
        )
        flat, unravel = jax.flatten_util.ravel_pytree(theta)
        jac = jax.jit(jax.jacfwd(lambda f: res(unravel(f)).reshape(-1)))(flat)
        norms = unravel(jnp.sqrt(jnp.sum(jac**2, axis=0)))
        r0 = np.asarray(res(theta))
    assert ss == pytest.approx(float(np.sum(r0**2)), rel=1e-12)
    for k, v in norms.items():
        v = np.asarray(v)
        assert v.min() > 0, k  # every parameter moves the residuals here
        np.testing.assert_allclose(np.asarray(got[k]), v, rtol=2e-5, err_msg=k)


def test_reduced_residual_has_the_full_gauss_newton_model(system):
    u, scale, keep, fit, *_ = system
    with jax.enable_x64(True):
        args = (scale, (jnp.asarray(True), keep, fit))
        flat, unravel = jax.flatten_util.ravel_pytree(u)
        res = jax.jit(lambda uf: F._fit_residuals_scaled(unravel(uf), args))
        red = res(flat)
        jt = jax.jit(jax.jacfwd(res))(flat)
        h_ref, b_ref, ss_ref = _dense(u, scale, keep, fit, jnp.asarray(True))
    # Profiled thresholds: their columns are zero and get a unit pivot (gradient 0).
    live = np.asarray(jnp.diag(h_ref) > 0)
    assert (~live).sum() == 2
    np.testing.assert_allclose(float(red @ red), float(ss_ref), rtol=1e-10)
    np.testing.assert_allclose((jt.T @ red)[live], b_ref[live], rtol=1e-7,
                               atol=1e-9 * float(jnp.max(abs(b_ref))))  # fmt: skip
    np.testing.assert_allclose(jt.T @ red, jnp.where(live, jt.T @ red, 0.0), atol=1e-12)
    gn = (jt.T @ jt)[np.ix_(live, live)]
    np.testing.assert_allclose(gn, h_ref[np.ix_(live, live)], rtol=1e-7,
                               atol=1e-9 * float(jnp.max(h_ref)))  # fmt: skip


@pytest.fixture(scope="module")
def noisy_chart():
    """A gray chart recorded for 8 sweeps by a sensor with per-crossing noise: more
    events per pixel than the fit's lists keep (256)."""
    h, w = 12, 8
    rig = ev.Rig(threshold_noise=0.01)
    chart = ev.load_scene("gray-chart", (h, w))
    events, info = ev.simulate(chart, rig, sweeps=8, key=jr.key(2), return_info=True)
    return rig, chart, events, info


def test_threshold_maps_in_row_bands_equal_one_pass(noisy_chart, monkeypatch):
    from evhsi_jax._calibrate import _chart as C

    rig, chart, events, _ = noisy_chart
    kw = dict(psf_sigmas_px=(0.0, 0.5), return_psf=True)
    whole = C.threshold_maps_from_chart(events, chart, rig, **kw)
    monkeypatch.setattr(C, "MAP_BLOCK_EVENTS", len(events) // 5)
    assert len(C._row_bands(events, C.MAP_BLOCK_EVENTS)) >= 5
    banded = C.threshold_maps_from_chart(events, chart, rig, **kw)
    assert banded[2] == whole[2]
    # Pixels with a stray event are refitted against their band's robust spread.
    for a, b in zip(banded[:2], whole[:2]):
        assert np.mean(np.isclose(a, b, rtol=0, atol=1e-12)) > 0.95
        np.testing.assert_allclose(a, b, atol=2e-3)


def test_threshold_maps_use_every_event_of_a_long_chart(noisy_chart, monkeypatch):
    from evhsi_jax._calibrate import _chart as C

    rig, chart, events, info = noisy_chart
    counts = np.bincount(events.y.astype(np.int64) * events.width + events.x)
    assert counts.max() > 256  # the fit's lists would cut these pixels short

    def err(maps):
        return float(np.sqrt(np.mean((maps[0] - info.threshold_on) ** 2)))

    kw = dict(psf_sigmas_px=(0.0,))
    all_events = err(C.threshold_maps_from_chart(events, chart, rig, **kw))
    monkeypatch.setattr(C, "MAP_MAX_EVENTS", 48)  # about one sweep
    first_sweep = err(C.threshold_maps_from_chart(events, chart, rig, **kw))
    # ~8x the events: the noise part of the error averages down (the rest is the
    # censoring of crossings near the sweep's peak, the same for both).
    assert all_events < 0.8 * first_sweep


def test_log_steps_share_one_program_across_spectra_and_pixel_counts(
    noisy_chart, monkeypatch
):
    """`_log_steps` pads the chart's spectra (to `MIN_SPECTRA` or a power of two) and a
    small set of pixels (to a power of two), so lists with 6 or 11 spectra and 40 or
    60 pixels run one program (a first calibration compiled ~11 of these, ~0.8 s each
    with a photoreceptor); the padding changes no step."""
    from evhsi_jax._calibrate import _chart as C

    rig, chart, events, _ = noisy_chart
    rig = C._with_column_offsets(rig, events.width)
    data = chart_data(events, chart, rig)
    shapes = set()
    real = C.call_exported

    def spy(name, fn, args, **kw):
        if name == "chart_log_steps":
            shapes.add(tuple(np.shape(a) for a in jax.tree.leaves(args)))
        return real(name, fn, args, **kw)

    monkeypatch.setattr(C, "call_exported", spy)
    with jax.enable_x64(True):
        rig = rig.astype(jnp.float64)
        for n_px in (40, 60):
            for extra in (0, 5):  # unused spectra appended: 6 or 11 in all
                sub = C.dataclasses.replace(
                    data.subset(slice(0, n_px)),
                    spectra=np.concatenate([data.spectra, data.spectra[:extra]]),
                )
                steps = C._log_steps(rig, sub)
                direct = np.asarray(C.chart_log_steps(rig, sub))
                np.testing.assert_allclose(steps, direct, rtol=1e-10, atol=1e-12)
    assert len(shapes) == 1, shapes


def test_new_captures_of_a_chart_share_the_fits_programs():
    """The fit's programs are keyed by their inputs' structure and shapes
    (`call_exported`): two captures of one chart (other thresholds, other noise)
    and another band profile in the start give the same, so a user's next
    calibration runs the programs the last one compiled (README, Performance,
    "Calibration's memory and time"). Each list entry up to a pixel's last event has
    a slot of its own."""
    h, w = 12, 8
    chart = ev.load_scene("gray-chart", (h, w))
    truth = ev.Rig(threshold_noise=0.02)
    sigs = []
    for seed, start in ((1, ev.Rig()), (2, ev.Rig().with_band_profile("skewed"))):
        events = ev.simulate(chart, truth, sweeps=2, key=jr.key(seed))
        with jax.enable_x64(True):
            rig = F._with_column_offsets(start, w).astype(jnp.float64)
            data = chart_data(events, chart, rig, rows_per_label=None)
            blocks, layout = F._packed(data, jnp.float64)
            n = data.t_us.shape[0]
            assert np.unique(layout.slot).size == layout.slot.size
            assert np.asarray(blocks.mask).sum() == data.mask.sum()
            fit = F._fit_data(rig, F._response_basis(rig, 2), blocks, data.spectra,
                              None, band_overlap(rig), None, jnp.ones((), jnp.float64),
                              True)  # fmt: skip
            keep = layout.per_slot(np.ones(n), np.float64)
            leaves, treedef = jax.tree.flatten((keep, fit))
            sigs.append((treedef, [np.shape(a) for a in leaves], data.mask.sum()))
    assert sigs[0][2] != sigs[1][2]  # other captures: other event counts
    assert sigs[0][:2] == sigs[1][:2]


def test_block_counts_are_rounded_to_few_values():
    small = {F._blocks_of(n) for n in range(1, F.SMALL_BLOCKS + 1)}
    assert small == {1, 2, 4, 8, 16}
    for need in range(F.SMALL_BLOCKS + 1, 5000, 7):
        got = F._blocks_of(need)
        assert need <= got <= need * (1 + 1 / 16)


@pytest.mark.parametrize("per_pixel", [False, True])
def test_packed_residuals_and_tangents_are_the_lists(system, per_pixel):
    """The packed blocks' residuals are the chart lists' (`chart_residuals`, whose
    profiled derivative test_calibrate.py checks against the automatic one), event
    for event; and so are their tangents, along a direction of the traces and one
    that also changes C_on, from `packed_scaled_tangents`' batched rule and from
    `jax.jvp` of the lists' residuals."""
    from evhsi_jax._calibrate import _chart as C

    *_, data, blocks, layout = system
    with jax.enable_x64(True):
        rig = F._with_column_offsets(ev.Rig(photoreceptor_hz=20000.0), data.width)
        rig = rig.astype(jnp.float64)
        traces = C.spectral_traces(rig, data.spectra)
        dirs = jr.normal(jr.key(3), (2,) + traces.values.shape, jnp.float64)

        def lists(log_on, tv):
            r = rig.with_leaves(threshold_on=rig.threshold_on * jnp.exp(log_on))
            tab = C.BandTable(tv, traces.lo_nm, traces.step_nm)
            return C.chart_residuals(r, data, tab, per_pixel=per_pixel)

        zero = jnp.zeros((), jnp.float64)
        want = [lists(zero, traces.values)]
        for i, dlog in enumerate((0.0, 1.0)):
            tangent = (jnp.asarray(dlog), dirs[i])
            want.append(jax.jvp(lists, (zero, traces.values), tangent)[1])

        def packed(block):
            def steps(tv):
                tab = C.BandTable(tv, traces.lo_nm, traces.step_nm)
                return C.packed_log_steps(rig, block, tab)

            d, lin = jax.linearize(steps, traces.values)
            dd = jax.vmap(lin)(dirs)
            inv = jnp.stack([1.0 / rig.threshold_on, 1.0 / rig.threshold_off])
            d_inv = jnp.stack([jnp.zeros(2), jnp.stack([-inv[0], 0.0 * inv[1]])])
            r, dr = C.packed_scaled_tangents(block, d, dd, inv, d_inv, per_pixel)
            return r, dr, C.packed_scaled(rig, block, d, per_pixel)

        r, dr, direct = jax.jit(jax.vmap(packed))(blocks)
    np.testing.assert_array_equal(np.asarray(r), np.asarray(direct))
    got = [layout.to_lists(r)] + [layout.to_lists(dr[:, i]) for i in range(2)]
    for g, w in zip(got, want, strict=True):
        w = np.asarray(w)
        np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-12 * np.abs(w).max())


@pytest.mark.parametrize("cutoff_hz", [0.0, 20000.0], ids=["ideal", "low-pass"])
def test_packed_log_step_tangents_are_the_jvps(packed, cutoff_hz):
    """`packed_log_step_tangents` (the table read once for every tangent) against
    `jax.jvp` of `packed_log_steps` along each direction: directions that move β,
    the baseline, the sweep's curvature, the refractory time and every column offset
    together with the table the events read (the traces, or their low-passed log
    levels)."""
    from evhsi_jax._calibrate import _chart as C

    _, data, blocks, _ = packed
    w = data.width
    with jax.enable_x64(True):
        rig = F._with_column_offsets(ev.Rig(photoreceptor_hz=cutoff_hz), w)
        rig = rig.astype(jnp.float64)
        tab = C.spectral_traces(rig, data.spectra)
        if cutoff_hz:
            tab = C.lowpassed_traces(rig, tab)

        def rig_at(u):
            return rig.with_leaves(
                beta_nm_per_rad=rig.beta_nm_per_rad * jnp.exp(u[0]),
                baseline_rel=rig.baseline_rel + u[1],
                sweep_curvature_nm=u[2],
                refractory_us=rig.refractory_us + u[3],
                column_offsets_us=rig.column_offsets_us + u[4:],
            )

        u = jnp.concatenate([jnp.asarray([0.01, 0.02, 0.5, 1.0]), jnp.zeros(w)])
        t = 3
        tans = jr.normal(jr.key(7), (t, u.size), jnp.float64)
        d_tab = jr.normal(jr.key(8), (t,) + tab.values.shape, jnp.float64)
        # The offsets' tangents: the last w entries of each direction.
        offsets = jnp.concatenate([rig_at(u).column_offsets(w)[:, None], tans[:, 4:].T], 1)
        stacked = jnp.concatenate([tab.values[..., None], jnp.moveaxis(d_tab, 0, -1)], -1)
        table = C.BandTable(stacked, tab.lo_nm, tab.step_nm)

        def steps(u, tv, block):
            t_ = C.BandTable(tv, tab.lo_nm, tab.step_nm)
            return C.packed_log_steps(rig_at(u), block, t_, t_ if cutoff_hz else None)

        def both(block):
            d, dd = C.packed_log_step_tangents(rig_at, u, tans, block, table, offsets)
            want = [steps(u, tab.values, block)]
            for i in range(t):
                want.append(jax.jvp(lambda u, tv: steps(u, tv, block),
                                    (u, tab.values), (tans[i], d_tab[i]))[1])  # fmt: skip
            return d, dd, jnp.stack(want)

        d, dd, want = jax.jit(jax.vmap(both))(blocks)
    assert float(jnp.abs(want[:, 1:]).max()) > 0.0
    np.testing.assert_allclose(d, want[:, 0], rtol=1e-12, atol=1e-12)
    scale = float(jnp.abs(want[:, 1:]).max())
    np.testing.assert_allclose(
        jnp.moveaxis(dd, 1, 0), jnp.moveaxis(want[:, 1:], 1, 0), rtol=1e-10,
        atol=1e-12 * scale,
    )  # fmt: skip
