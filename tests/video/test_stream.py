"""Streaming per-sweep reconstruction: accuracy, the carried reference, resuming,
flags, chunk independence, the dataset format and the CLI."""

import dataclasses
import json

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._model._dynamic import changed_pixels, dynamic_scene
from evhsi_jax._video._stream import (
    INDEX_NAME,
    LOCK_NAME,
    iter_sweep_cubes,
    load_sweep_index,
    reconstruct_sweeps,
    sweep_file_name,
)
from evhsi_jax.cli import main

SIZE = (6, 10)
SWEEPS = 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    rig = ev.Rig()
    scenes = dynamic_scene("translate", SIZE, sweeps=SWEEPS, velocity_px_per_sweep=1.0)
    events, info = ev.simulate(
        scenes, rig, sweeps=SWEEPS, key=jr.key(3), return_info=True
    )
    folder = tmp_path_factory.mktemp("rec")
    path = folder / "ev.raw"
    ev.write_events(path, events)
    kw = dict(threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off)
    return rig, scenes, events, path, kw


@pytest.fixture(scope="module")
def full_run(recording, tmp_path_factory):
    rig, _, _, path, kw = recording
    out = tmp_path_factory.mktemp("full") / "cubes"
    res = reconstruct_sweeps(path, rig, out, **kw)
    return out, res


def _cubes(out):
    return [c["cube"] for _, c in iter_sweep_cubes(out)]


def test_one_cube_per_sweep_with_the_sweep_accuracy(recording, full_run):
    rig, scenes, events, _, _ = recording
    out, res = full_run
    assert (res.sweeps, res.reconstructed, res.skipped) == (SWEEPS, SWEEPS, 0)
    index = load_sweep_index(out)
    assert index["complete"] and index["boundaries"] == "trigger"
    assert [e["start_us"] for e in index["sweeps"]] == events.trigger_t_us.tolist()
    assert sum(e["events"] for e in index["sweeps"]) == len(events)
    changed = changed_pixels(scenes, rig.grid)
    for (entry, data), scene, chg in zip(iter_sweep_cubes(out), scenes, changed):
        cube = data["cube"]
        assert cube.shape == (*SIZE, rig.channels) and cube.dtype == np.float32
        assert data["srgb"].dtype == np.uint8 and int(data["sweep"]) == entry["sweep"]
        sam = ev.metrics.sam_map_deg(cube, scene.truth_cube(rig.grid))
        assert sam[~chg].mean() < 6.0, entry  # unchanged pixels: as a static scene
    assert (out / "preview.gif").read_bytes()[:6] == b"GIF89a"


def test_carried_reference_beats_the_baseline(recording, full_run):
    """Later sweeps start from the reference their last events left; taking the
    baseline at the sweep start instead is wrong by up to a threshold."""
    rig, scenes, events, _, kw = recording
    out, _ = full_run
    sw = ev.io.split_sweeps(events)
    k = 2
    truth = scenes[k].truth_cube(rig.grid)
    naive = ev.reconstruct(sw[k], rig, t_start_us=int(sw.start_us[k]), **kw)
    carried = _cubes(out)[k]
    assert ev.metrics.sam_deg(carried, truth) < ev.metrics.sam_deg(naive, truth) - 2.0


def test_interrupted_run_resumes_without_redoing_or_corrupting(recording, full_run):
    rig, _, _, path, kw = recording
    out = full_run[0].parent / "interrupted"

    class Crash(Exception):
        pass

    def crash_after_two(entry):
        if entry["sweep"] == 1:
            raise Crash

    with pytest.raises(Crash):
        reconstruct_sweeps(path, rig, out, on_sweep=crash_after_two, **kw)
    files = sorted(p.name for p in out.iterdir())
    assert files == [LOCK_NAME, INDEX_NAME, sweep_file_name(0), sweep_file_name(1)]  # no temp
    index = load_sweep_index(out)
    assert not index["complete"] and [e["sweep"] for e in index["sweeps"]] == [0, 1]
    res = reconstruct_sweeps(path, rig, out, **kw)
    assert (res.skipped, res.reconstructed, res.sweeps) == (2, 1, SWEEPS)
    for a, b in zip(_cubes(out), _cubes(full_run[0]), strict=True):
        assert np.array_equal(a, b)  # the resumed carry is the uninterrupted one
    again = reconstruct_sweeps(path, rig, out, **kw)
    assert (again.skipped, again.reconstructed) == (SWEEPS, 0)


def test_files_newer_than_the_index_are_adopted(recording, full_run):
    rig, _, _, path, kw = recording
    out = full_run[0].parent / "stale_index"
    out.mkdir()
    for p in full_run[0].iterdir():
        (out / p.name).write_bytes(p.read_bytes())
    index = json.loads((out / INDEX_NAME).read_text())
    index["sweeps"] = index["sweeps"][:1]  # as if it crashed before catching up
    (out / INDEX_NAME).write_text(json.dumps(index))
    (out / sweep_file_name(2)).unlink()
    res = reconstruct_sweeps(path, rig, out, **kw)
    assert (res.skipped, res.reconstructed) == (2, 1)


def test_other_settings_are_refused_unless_overwriting(recording, full_run):
    rig, _, _, path, kw = recording
    out = full_run[0].parent / "refuse"
    reconstruct_sweeps(path, rig, out, max_sweeps=1, preview=False, **kw)
    with pytest.raises(ValueError, match="other inputs or settings"):
        reconstruct_sweeps(path, rig, out, solver="unconstrained", **kw)
    res = reconstruct_sweeps(
        path, rig, out, solver="unconstrained", overwrite=True, preview=False, **kw
    )
    assert (res.reconstructed, res.skipped) == (SWEEPS, 0)


def test_dark_sweep_is_flagged(recording, tmp_path):
    rig, _, events, _, kw = recording
    sw = ev.io.split_sweeps(events)
    keep = sw.sweep_index() != 1  # occlusion: sweep 1 sends almost nothing
    keep |= np.arange(len(events)) % 50 == 0
    dark = events.take(np.flatnonzero(keep))
    res = reconstruct_sweeps(dark, rig, tmp_path / "d", preview=False, **kw)
    assert res.low_event_sweeps == [1]
    entry = res.index["sweeps"][1]
    assert entry["low_events"] and entry["events_rel"] < 0.1
    assert all(np.isfinite(c).all() for c in _cubes(tmp_path / "d"))


def test_small_read_chunks_and_no_triggers_give_the_same_sweeps(recording, tmp_path):
    rig, _, events, path, kw = recording
    res_small = reconstruct_sweeps(
        path, rig, tmp_path / "s", chunk_bytes=2048, preview=False, **kw
    )
    assert res_small.index["sweeps"] == [
        {**e, "seconds": e2["seconds"]}
        for e, e2 in zip(
            load_sweep_index(tmp_path / "s")["sweeps"], res_small.index["sweeps"]
        )
    ]
    bare = dataclasses.replace(
        events,
        trigger_t_us=events.trigger_t_us[:0],
        trigger_p=events.trigger_p[:0],
        trigger_id=events.trigger_id[:0],
    )
    res_bare = reconstruct_sweeps(bare, rig, tmp_path / "b", preview=False, **kw)
    starts = [e["start_us"] for e in res_bare.index["sweeps"]]
    assert res_bare.index["boundaries"] == "period"
    assert starts == events.trigger_t_us.tolist()  # round(k P), as the triggers
    for a, b in zip(_cubes(tmp_path / "s"), _cubes(tmp_path / "b"), strict=True):
        assert np.array_equal(a, b)


def test_cli_per_sweep(recording, tmp_path, capsys):
    rig, _, _, path, _ = recording
    calib = tmp_path / "calib.json"
    calib.write_text('{"threshold_on": 0.15}')
    out = tmp_path / "video"
    argv = ["reconstruct", str(path), "--calib", str(calib), "--out", str(out)]
    assert main([*argv, "--per-sweep", "--quiet", "--max-sweeps", "2"]) == 0
    assert "2 reconstructed" in capsys.readouterr().out
    assert main([*argv, "--per-sweep", "--quiet"]) == 0
    assert "2 already done" in capsys.readouterr().out
    assert load_sweep_index(out)["complete"]
    assert main([*argv, "--max-sweeps", "2"]) == 2  # per-sweep options need the flag
    assert "only with --per-sweep" in capsys.readouterr().err
    assert main([*argv[:-1], str(tmp_path / "x.npz"), "--per-sweep"]) == 2
    assert "is a folder" in capsys.readouterr().err
