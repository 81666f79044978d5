"""Cube formats by extension: `.npz`, ENVI `.hdr` (checked with Spectral Python itself),
`.zarr` (checked with xarray itself), and the per-sweep video store."""

import json

import jax.random as jr
import numpy as np
import pytest
import spectral.io.envi as envi
import xarray as xr
import zarr

import evhsi_jax as ev
from evhsi_jax._video._store import VideoStore
from evhsi_jax.cli import main

H, W = 4, 6


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("cubes")
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", (H, W))
    events = ev.simulate(scene, rig, sweeps=2, key=jr.key(2))
    ev.write_events(d / "ev.npz", events)
    (d / "cal.json").write_text("{}")
    return d, events, scene.truth_cube(rig.grid), rig.wavelengths_nm


def _cube(seed=0, m=7):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (3, 5, m)).astype(np.float32), np.linspace(405, 695, m)


def test_envi_is_read_by_spectral_python(tmp_path):
    cube, wl = _cube()
    cube[1, 2, 3] = np.nan
    labels = np.arange(15).reshape(3, 5)
    ev.save_cube(tmp_path / "c.hdr", cube, wl, labels=labels)
    img = envi.open(str(tmp_path / "c.hdr"))
    data = np.asarray(img.load())
    assert data.shape == cube.shape and data.dtype == np.float32
    np.testing.assert_allclose(img.bands.centers, wl, rtol=0, atol=1e-4)
    assert img.metadata["wavelength units"] == "Nanometers"
    assert float(img.metadata["data ignore value"]) == -1.0
    ok = np.isfinite(cube)
    assert np.array_equal(data[ok], cube[ok]) and data[1, 2, 3] == -1.0
    back = ev.load_cube(tmp_path / "c.hdr")
    assert np.array_equal(back["cube"][ok], cube[ok]) and np.isnan(back["cube"][1, 2, 3])
    assert np.array_equal(back["labels"], labels)
    np.testing.assert_allclose(back["wavelengths_nm"], wl, atol=1e-4)
    assert ev.load_cube(tmp_path / "c.img")["cube"].shape == cube.shape


def test_envi_written_elsewhere_is_read(tmp_path):
    cube, wl = _cube(1)
    envi.save_image(str(tmp_path / "f.hdr"), cube, metadata={
        "wavelength": [str(v / 1000) for v in wl], "wavelength units": "Micrometers",
    }, interleave="bil", ext=".raw")  # fmt: skip
    back = ev.load_cube(tmp_path / "f.hdr")
    assert np.array_equal(back["cube"], cube)
    np.testing.assert_allclose(back["wavelengths_nm"], wl, rtol=1e-9)


def test_zarr_cube_is_read_by_xarray(tmp_path):
    cube, wl = _cube(2)
    names = np.array(["a", "bb"])
    ev.save_cube(tmp_path / "c.zarr", cube, wl, kkt=cube[..., 0], names=names)
    ds = xr.open_zarr(tmp_path / "c.zarr")
    assert ds["reflectance"].dims == ("y", "x", "wavelength")
    assert np.array_equal(ds["reflectance"].values, cube)
    assert np.array_equal(ds["wavelength"].values, wl)
    back = ev.load_cube(tmp_path / "c.zarr")
    assert np.array_equal(back["cube"], cube) and list(back["names"]) == ["a", "bb"]
    ev.save_cube(tmp_path / "c.zarr", cube * 0.5, wl)  # replaced whole
    assert np.array_equal(ev.load_cube(tmp_path / "c.zarr")["cube"], cube * 0.5)
    assert "kkt" not in ev.load_cube(tmp_path / "c.zarr")


def test_cli_writes_and_reads_every_format(capture, capsys, tmp_path):
    d, _, truth, wl = capture
    outs = {}
    for ext in ("npz", "hdr", "zarr"):
        out = tmp_path / f"cube.{ext}"
        assert main(["reconstruct", str(d / "ev.npz"), "--calib", str(d / "cal.json"),
                     "--out", str(out), "--quiet"]) == 0  # fmt: skip
        outs[ext] = ev.load_cube(out)
    for ext in ("hdr", "zarr"):
        assert np.array_equal(outs[ext]["cube"], outs["npz"]["cube"])
        assert np.array_equal(outs[ext]["events_per_pixel"], outs["npz"]["events_per_pixel"])
    ev.save_cube(tmp_path / "truth.hdr", truth, wl)
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "cube.zarr"), "--truth",
                 str(tmp_path / "truth.hdr"), "--json"]) == 0  # fmt: skip
    via_formats = json.loads(capsys.readouterr().out)
    stored_truth = ev.load_cube(tmp_path / "truth.hdr")["cube"]  # float32 on disk
    assert via_formats == ev.evaluate(outs["npz"]["cube"], stored_truth)
    assert main(["render", str(tmp_path / "cube.hdr"), "--out", str(tmp_path / "c.png")]) == 0
    assert main(["convert", str(tmp_path / "cube.hdr"), str(tmp_path / "back.npz")]) == 0
    assert np.array_equal(ev.load_cube(tmp_path / "back.npz")["cube"], outs["npz"]["cube"])


def test_reconstruct_on_fewer_channels_and_evaluate_with_resampling(capture, capsys, tmp_path):
    d, events, truth, wl = capture
    ev.save_cube(tmp_path / "truth.npz", truth, wl)
    out = tmp_path / "c36.npz"
    assert main(["reconstruct", str(d / "ev.npz"), "--calib", str(d / "cal.json"),
                 "--out", str(out), "--channels", "36", "--quiet"]) == 0  # fmt: skip
    got = ev.load_cube(out)
    rig36 = ev.Rig().with_channels(36)
    assert got["cube"].shape == (H, W, 36)
    np.testing.assert_allclose(got["wavelengths_nm"], rig36.wavelengths_nm)
    # the same cube as the Python API on the 36-channel calibration
    np.testing.assert_array_equal(got["cube"], ev.reconstruct(events, rig36))
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(tmp_path / "truth.npz")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--resample" in err
    assert main(["evaluate", str(out), "--truth", str(tmp_path / "truth.npz"),
                 "--resample", "--json"]) == 0  # fmt: skip
    io = capsys.readouterr()
    w = ev.forward.resample_matrix(rig36.wavelengths_nm, wl)
    assert json.loads(io.out) == ev.evaluate(np.asarray(got["cube"], np.float64) @ w.T, truth)
    assert "resampled from 36 to 72" in io.err
    # weights summing to 1, interpolating a line exactly between the cube's centres
    # (beyond its first and last centre, half a channel: the end value)
    np.testing.assert_allclose(w.sum(1), 1.0)
    assert (np.count_nonzero(w, axis=1) <= 2).all()
    np.testing.assert_allclose((w @ rig36.wavelengths_nm)[1:-1], wl[1:-1])
    assert (w @ rig36.wavelengths_nm)[0] == rig36.wavelengths_nm[0]
    for bad in ("1", "5000"):
        code = main(["reconstruct", str(d / "ev.npz"), "--calib", str(d / "cal.json"),
                     "--out", str(tmp_path / "x.npz"), "--channels", bad])  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and "--channels" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "x.npz").exists()


def test_bad_cube_files_are_one_line_errors(capsys, tmp_path):
    cube, wl = _cube(3)
    ev.save_cube(tmp_path / "c.hdr", cube, wl)
    (tmp_path / "c.img").write_bytes((tmp_path / "c.img").read_bytes()[:100])
    (tmp_path / "junk.hdr").write_text("not an envi header\n")
    (tmp_path / "junk.zarr").mkdir()
    for name in ("c.hdr", "junk.hdr", "junk.zarr", "nothing.hdr"):
        code = main(["render", str(tmp_path / name), "--out", str(tmp_path / "x.png")])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert name in err


def test_video_store_equals_the_folder_and_resumes(capture, tmp_path):
    d, events, _, wl = capture
    cal = ev.Calibration(ev.Rig())
    ev.reconstruct_sweeps(events, cal, tmp_path / "dir")
    res = ev.reconstruct_sweeps(events, cal, tmp_path / "v.zarr")
    assert res.reconstructed == 2
    ds = xr.open_zarr(tmp_path / "v.zarr")
    assert ds["reflectance"].dims == ("time", "y", "x", "wavelength")
    assert np.array_equal(ds["wavelength"].values, wl)
    folder = list(ev.video.iter_sweep_cubes(tmp_path / "dir"))
    assert list(ds["time"].values) == [e["start_us"] for e, _ in folder]
    for (_, a), (_, b) in zip(folder, ev.video.iter_sweep_cubes(tmp_path / "v.zarr")):
        assert np.array_equal(a["cube"], b["cube"])
    for i, (_, a) in enumerate(folder):
        assert np.array_equal(ds["reflectance"].values[i], a["cube"])
    # each sweep's mirror-speed factor, as the folder's index has it
    speeds = [e["sweep_speed"] for e, _ in folder]
    assert np.array_equal(ds["sweep_speed"].values, speeds)
    assert [e["sweep_speed"] for e in VideoStore(tmp_path / "v.zarr").entries()] == speeds
    # A run killed after writing part of a third sweep: arrays longer than `time`,
    # a temporary file of zarr's. The next run cuts back, cleans up, skips the rest.
    g = zarr.open_group(str(tmp_path / "v.zarr"), mode="a")
    g["reflectance"].append(np.zeros((1, H, W, len(wl)), np.float32), axis=0)
    (tmp_path / "v.zarr" / "reflectance" / "c" / "x.partial").write_bytes(b"..")
    res = ev.reconstruct_sweeps(events, cal, tmp_path / "v.zarr")
    assert (res.reconstructed, res.skipped, res.stale_removed) == (0, 2, 1)
    assert zarr.open_group(str(tmp_path / "v.zarr"))["reflectance"].shape[0] == 2
    # converting the folder gives the same store contents; one sweep back to a cube
    assert main(["convert", str(tmp_path / "dir"), str(tmp_path / "c.zarr")]) == 0
    conv = xr.open_zarr(tmp_path / "c.zarr")
    assert np.array_equal(conv["reflectance"].values, ds["reflectance"].values)
    assert np.array_equal(conv["sweep_speed"].values, speeds)
    assert main(["convert", str(tmp_path / "v.zarr"), str(tmp_path / "s1.hdr"),
                 "--sweep", "1"]) == 0  # fmt: skip
    assert np.array_equal(ev.load_cube(tmp_path / "s1.hdr")["cube"], folder[1][1]["cube"])
    with pytest.raises(ValueError, match="video store of 2 sweeps"):
        ev.load_cube(tmp_path / "v.zarr")
