"""The rig: defaults of DESIGN.md, derived quantities, JSON contract and validation."""

from __future__ import annotations

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax import Rig
from evhsi_jax._model._rig import DEFAULTS
from evhsi_jax.forward import SpectralGrid

# DESIGN.md, "Defaults: the paper's simulated rig" and the JSON key list.
DESIGN_DEFAULTS = {
    "channels": 72,
    "channel_start_nm": 400.0,
    "channel_stop_nm": 760.0,
    "fwhm_nm": 17.5,
    "samples_per_sweep": 1200,
    "sweep_rate_hz": 30.0,
    "threshold_on": 0.15,
    "threshold_off": 0.15,
    "threshold_sigma": 0.01,
    "refractory_us": 50.0,
    "baseline_rel": 0.03,
}
CONTRACT_KEYS = set(DESIGN_DEFAULTS) | {"beta_nm_per_rad", "column_offsets_us", "seed"}


@pytest.mark.parametrize("key, value", sorted(DESIGN_DEFAULTS.items()))
def test_defaults_match_design(key, value):
    d = Rig().to_dict()
    assert d[key] == pytest.approx(value, rel=1e-6)


def test_default_derived_quantities():
    rig = Rig()
    assert rig.grid == SpectralGrid(72, 400.0, 760.0, 1.0)
    assert rig.reset_mode == "release"
    np.testing.assert_allclose(rig.wavelengths_nm, 402.5 + 5.0 * np.arange(72))
    np.testing.assert_allclose(float(rig.period_us), 1e6 / 30.0, rtol=1e-6)
    # ω is half the mirror speed: 1800 rpm = 30 rev/s → π·30 rad/s.
    np.testing.assert_allclose(float(rig.omega_rad_per_us), math.pi * 30e-6, rtol=1e-6)
    # Camera response and lamp live on the 1 nm fine grid, peak 1.
    assert rig.camera_response.shape == rig.lamp.shape == (360,)
    np.testing.assert_allclose(float(jnp.max(rig.lamp)), 1.0, rtol=1e-6)


@pytest.mark.parametrize("width", [1, 6, 1280])
def test_default_column_offsets(width):
    rig = Rig()
    period = 1e6 / 30.0
    want = (
        np.zeros(1) if width == 1 else -0.15 * period * np.arange(width) / (width - 1)
    )
    np.testing.assert_allclose(np.asarray(rig.column_offsets(width)), want, atol=1e-2)
    d = rig.to_dict(width)
    assert len(d["column_offsets_us"]) == width
    np.testing.assert_allclose(d["column_offsets_us"], want, atol=1e-2)


@pytest.mark.parametrize("t_us", [0.0, 1234.5, 20000.0, 33333.0, 33334.0, 70000.0])
@pytest.mark.parametrize("offset_us", [0.0, -2500.0])
def test_band_centre_formula(t_us, offset_us):
    with jax.enable_x64(True):
        rig = Rig(beta_nm_per_rad=170.0, sweep_start_nm=355.0, sweep_rate_hz=25.0)
        got = float(rig.band_centre_nm(jnp.asarray(t_us), jnp.asarray(offset_us)))
    period = 1e6 / 25.0
    omega = math.pi * 25.0 * 1e-6
    want = 355.0 + 170.0 * omega * (math.fmod(t_us, period) + offset_us)
    assert got == pytest.approx(want, abs=1e-9)


def test_every_contract_key_resolved():
    d = Rig().to_dict(width=8)
    assert CONTRACT_KEYS <= set(d)
    assert set(DEFAULTS) <= set(d)
    json.dumps(d)  # plain JSON types only


def test_describe_keys_names_every_key():
    text = Rig.describe_keys()
    for k in DEFAULTS:
        assert k in text


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"fwhm_nm": 12.0, "threshold_on": 0.2, "threshold_off": 0.11, "seed": 3},
        {"column_offsets_us": [0.0, -10.0, -20.0, -30.5]},
        {
            "camera_response": {
                "wavelengths_nm": [380.0, 600.0, 780.0],
                "values": [0.2, 1.0, 0.5],
            },
            "lamp": {"wavelengths_nm": [390.0, 770.0], "values": [2.0, 1.0]},
        },
        {"channels": 36, "channel_start_nm": 420.0, "reset_mode": "event"},
    ],
)
def test_json_round_trip(tmp_path, overrides):
    rig = Rig.from_dict(overrides)
    path = tmp_path / "rig.json"
    rig.save(path)
    back = Rig.load(path)
    assert back.to_dict() == rig.to_dict()
    # The leaves too, not only their JSON rendering.
    for a, b in zip(jax.tree.leaves(rig), jax.tree.leaves(back)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert json.loads(path.read_text()) == rig.to_dict()


def test_custom_spectra_are_resampled_and_normalised():
    rig = Rig(camera_response={"wavelengths_nm": [380.0, 780.0], "values": [1.0, 3.0]})
    fine = rig.grid.fine_centres_nm
    want = 1.0 + 2.0 * (fine - 380.0) / 400.0
    np.testing.assert_allclose(
        np.asarray(rig.camera_response), want / want.max(), rtol=1e-6
    )


def test_file_overriding_one_key(tmp_path):
    path = tmp_path / "one.json"
    path.write_text('{"fwhm_nm": 20}\n')
    rig = Rig.load(path)
    got, ref = rig.to_dict(width=5), Rig().to_dict(width=5)
    assert got["fwhm_nm"] == 20.0
    got.pop("fwhm_nm")
    ref.pop("fwhm_nm")
    assert got == ref


def test_saved_with_width_fills_offsets(tmp_path):
    path = tmp_path / "rig.json"
    Rig().save(path, width=6)
    back = Rig.load(path)
    np.testing.assert_allclose(
        np.asarray(back.column_offsets(6)), np.asarray(Rig().column_offsets(6))
    )


def test_leaves_follow_x64():
    assert Rig().fwhm_nm.dtype == jnp.float32
    with jax.enable_x64(True):
        rig = Rig()
        assert rig.fwhm_nm.dtype == jnp.float64
        assert rig.camera_response.dtype == jnp.float64


def test_tree_at_updates_a_leaf():
    rig = Rig()
    new = eqx.tree_at(lambda r: r.beta_nm_per_rad, rig, jnp.asarray(190.0))
    assert float(new.beta_nm_per_rad) == 190.0
    assert float(rig.beta_nm_per_rad) == 185.0


@pytest.mark.parametrize(
    "data, match",
    [
        ({"fwhm_nm": -3.0}, "fwhm_nm"),
        ({"fwhm_nm": 0.0}, "fwhm_nm"),
        ({"threshold_on": 0.0}, "threshold_on"),
        ({"threshold_off": -0.1}, "threshold_off"),
        ({"refractory_us": 0}, "refractory_us"),
        ({"baseline_rel": -0.01}, "baseline_rel"),
        ({"threshold_sigma": -1.0}, "threshold_sigma"),
        ({"sweep_rate_hz": float("nan")}, "sweep_rate_hz"),
        ({"fwhm_nm": float("inf")}, "fwhm_nm"),
        ({"fwhm_nm": "wide"}, "fwhm_nm.*number"),
        ({"fwhm_nm": "17.5"}, "fwhm_nm.*number"),
        ({"fwhm_nm": None}, "fwhm_nm.*number"),
        ({"fwhm_nm": True}, "fwhm_nm.*number"),
        ({"beta_nm_per_rad": [185.0]}, "beta_nm_per_rad.*number"),
        ({"sweep_start_nm": "low"}, "sweep_start_nm.*number"),
        ({"sweep_start_nm": False}, "sweep_start_nm.*number"),
        ({"channels": 72.5}, "channels.*integer"),
        ({"channels": "72"}, "channels.*integer"),
        ({"samples_per_sweep": 8}, "samples_per_sweep"),
        ({"reset_mode": "sometimes"}, "reset_mode"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"column_offsets_us": []}, "column_offsets_us"),
        ({"column_offsets_us": [0.0, "a"]}, "column_offsets_us"),
        ({"column_offsets_us": [[0.0, 1.0]]}, "column_offsets_us"),
        ({"column_offsets_us": [0.0, float("nan")]}, "column_offsets_us"),
        ({"camera_response": [1.0, 2.0]}, "camera_response"),
        (
            {"lamp": {"wavelengths_nm": [380.0, 780.0], "values": [1.0]}},
            "lamp",
        ),
        (
            {"lamp": {"wavelengths_nm": [380.0, 780.0], "values": [0.0, 0.0]}},
            "lamp",
        ),
        (  # 450-780 nm in 10 nm steps does not cover the 400 nm channel edge
            {
                "lamp": {
                    "wavelengths_nm": list(np.arange(450.0, 781.0, 10.0)),
                    "values": [1.0] * 34,
                }
            },
            "lamp.*span",
        ),
        ({"fwhm": 17.5}, "unknown rig key.*fwhm"),
        ({"channel_start_nm": 800.0}, "channel_start_nm"),
    ],
)
def test_validation_errors(data, match):
    with pytest.raises(ValueError, match=match):
        Rig.from_dict(data)


def test_offsets_of_wrong_length_for_sensor():
    rig = Rig.from_dict({"column_offsets_us": [0.0, -1.0, -2.0]})
    np.testing.assert_allclose(np.asarray(rig.column_offsets(3)), [0.0, -1.0, -2.0])
    with pytest.raises(ValueError, match="3 column offsets.*5 columns"):
        rig.column_offsets(5)


@pytest.mark.parametrize(
    "text, match",
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "JSON object"),
        ('{"threshold_on": -1}', "threshold_on"),
        ('{"colour": 1}', "unknown rig key"),
    ],
)
def test_load_bad_files(tmp_path, text, match):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as err:
        Rig.load(path)
    assert str(path) in str(err.value)


def test_load_missing_file(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        Rig.load(tmp_path / "absent.json")


def test_with_leaves_replaces_by_name_and_is_differentiable():
    rig = Rig()
    r2 = rig.with_leaves(fwhm_nm=jnp.asarray(20.0), threshold_on=jnp.asarray(0.2))
    assert float(r2.fwhm_nm) == 20.0 and float(r2.threshold_on) == pytest.approx(0.2)
    assert float(r2.threshold_off) == float(rig.threshold_off)  # untouched
    assert float(rig.fwhm_nm) == pytest.approx(17.5)  # original unchanged
    g = jax.grad(lambda x: rig.with_leaves(beta_nm_per_rad=x).beta_nm_per_rad ** 2)(3.0)
    assert float(g) == pytest.approx(6.0)
    # None leaves (no stored column offsets) can be filled.
    assert rig.with_leaves(column_offsets_us=jnp.zeros(4)).column_offsets_us.shape == (
        4,
    )
    with pytest.raises(AttributeError, match="grid"):
        rig.with_leaves(grid=None)  # static field
    with pytest.raises(AttributeError, match="nope"):
        rig.with_leaves(nope=1.0)


def test_host_settings_do_not_retrace_a_kernel_of_the_rig():
    """Host-side settings (seed, the simulated threshold spread, background rate, the
    post-solve channel gain, the non-structural sensor effects) are dynamic leaves:
    a jitted function of the whole rig is traced once whatever their values. A change
    of the model's structure (the photoreceptor switched on) does retrace, so the
    check can fail."""
    t = jnp.linspace(0.0, 30000.0, 7)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def centres(rig):
        return rig.band_centre_nm(t[:, None], rig.column_offsets_us[None, :])

    offs = {"column_offsets_us": [0.0, -10.0, -20.0]}
    ref = centres(Rig(**offs))
    for host in (
        {"seed": 7},
        {"threshold_sigma": 0.03},
        {"noise_rate_hz": 2.0},
        {"channel_gain": [1.1] * 72},
        {"threshold_noise": 0.02, "timestamp_jitter_us": 3.0, "latency_us": 40.0},
        {"hot_pixel_fraction": 0.01, "sweep_rate_jitter": 0.001, "psf_sigma_px": 0.5},
        {"on_off_correlation": 0.5, "hot_pixel_rate_hz": 50.0},
    ):
        np.testing.assert_array_equal(centres(Rig(**offs, **host)), ref)
    with pytest.raises(Exception, match="trace"):
        centres(Rig(**offs, photoreceptor_hz=3000.0))


def test_a_rig_file_naming_threshold_maps_is_not_read_as_a_bare_rig(tmp_path):
    """The maps would be silently lost (22 dB instead of 37 on the demo): `Rig.load`
    refuses and says what to call; `maps="ignore"` reads the rig alone."""
    (tmp_path / "calib.json").write_text(json.dumps({"threshold_map": "maps.npz"}))
    with pytest.raises(ValueError, match="load_calibration"):
        Rig.load(tmp_path / "calib.json")
    assert (
        Rig.load(tmp_path / "calib.json", maps="ignore").to_dict()["threshold_map"]
        is None
    )


def test_astype_casts_physics_and_keeps_host_values_exact():
    rig = Rig(threshold_noise=0.0123456789, noise_rate_hz=0.3, seed=3).astype(
        jnp.float32
    )
    assert rig.fwhm_nm.dtype == jnp.float32
    assert float(rig.effects.threshold_noise) == 0.0123456789
    assert rig.effects.threshold_noise.dtype == np.float64 and int(rig.seed) == 3
    assert rig.to_dict()["noise_rate_hz"] == 0.3


def test_load_calibration_refuses_a_map_name_that_is_not_a_file_name(tmp_path):
    from evhsi_jax import load_calibration

    (tmp_path / "calib.json").write_text(json.dumps({"threshold_map": 5}))
    with pytest.raises(ValueError, match="file name"):
        load_calibration(tmp_path / "calib.json")


def test_with_channels_keeps_the_rig_and_resamples_the_gains():
    gain = np.linspace(0.8, 1.2, 72)
    rig = ev.Rig.from_dict({
        "sensor": "realistic", "channel_gain": gain.tolist(),
        "camera_response": {"wavelengths_nm": [390.0, 600.0, 770.0], "values": [0.5, 1.0, 0.7]},
        "column_offsets_us": [0.0, 3.0, 7.0],
    })  # fmt: skip
    new = rig.with_channels(36)
    assert new.channels == 36 and new.grid.start_nm == 400 and new.grid.stop_nm == 760
    assert rig.with_channels(72) is rig
    a, b = rig.to_dict(), new.to_dict()
    changed = {k for k in a if a[k] != b[k]}
    assert changed == {"channels", "channel_gain"}  # band, sensor, offsets, spectra kept
    # the gain is linear in the centres, so its interpolation is exact
    centres = new.wavelengths_nm
    np.testing.assert_allclose(b["channel_gain"], 0.8 + 0.4 * (centres - 402.5) / 355, rtol=1e-12)
    # D(λ) from the file's spelling on the new fine grid, not the old fine samples
    want = ev.forward.resample([390.0, 600.0, 770.0], [0.5, 1.0, 0.7], new.grid.fine_centres_nm)
    np.testing.assert_allclose(np.asarray(new.camera_response), want / want.max(), rtol=1e-6)
    assert new.fwhm_nm.dtype == rig.fwhm_nm.dtype
    cal = ev.Calibration(rig, np.full((2, 3), 0.2), np.full((2, 3), 0.25))
    c36 = cal.with_channels(36)
    assert c36.rig.channels == 36 and c36.threshold_on is cal.threshold_on
    for bad in (1, 4097, True):
        with pytest.raises(ValueError, match="channels"):
            rig.with_channels(bad)
