"""Live reconstruction: a recording reconstructed while a writer process appends it at
its real rate (`reconstruct_sweeps(..., follow=True)`, `evhsi reconstruct --per-sweep
--follow`), every sweep equal to the run on the finished file; regions (`--roi`)."""

import signal
import subprocess
import sys
import time

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax.cli import main

H, W = 4, 6
SWEEPS = 12  # 0.4 s of recording at 30 sweeps/s


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("live")
    rig = ev.Rig()
    events = ev.simulate(ev.load_scene("colorchecker", (H, W)), rig, sweeps=SWEEPS,
                         key=jr.key(9))  # fmt: skip
    ev.write_events(d / "rec.raw", events)
    (d / "cal.json").write_text("{}")
    cal = ev.Calibration(rig)
    ev.reconstruct_sweeps(d / "rec.raw", cal, d / "offline", preview=False)
    return d, cal


def _writer(src, dst, speed=1.0):
    code = (
        "import sys; from evhsi_jax._io import replay_raw; "
        f"replay_raw(sys.argv[1], sys.argv[2], speed={speed})"
    )
    return subprocess.Popen([sys.executable, "-c", code, str(src), str(dst)])


def test_follow_a_file_being_written(recording, tmp_path):
    d, cal = recording
    live = tmp_path / "live.raw"
    writer = _writer(d / "rec.raw", live)
    try:
        while not live.exists() or live.stat().st_size == 0:
            time.sleep(0.01)
        seen = []
        t0 = time.perf_counter()
        res = ev.reconstruct_sweeps(
            live, cal, tmp_path / "out", follow=True, idle_timeout_s=2.0,
            preview=False, on_sweep=lambda e: seen.append(time.perf_counter() - t0),
        )  # fmt: skip
    finally:
        assert writer.wait(timeout=60) == 0
    assert res.reconstructed == SWEEPS and res.index["complete"]
    # sweeps were reconstructed while the file grew, not all at the end
    assert seen[0] < seen[-1] - 0.1
    offline = list(ev.video.iter_sweep_cubes(d / "offline"))
    for (e1, a), (e2, b) in zip(offline, ev.video.iter_sweep_cubes(tmp_path / "out")):
        assert (e1["start_us"], e1["events"]) == (e2["start_us"], e2["events"])
        np.testing.assert_array_equal(a["cube"], b["cube"])


def test_cli_follow_ends_on_idle_and_on_a_signal(recording, tmp_path, capsys):
    d, _ = recording
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert main(["reconstruct", str(d / "rec.raw"), "--calib", str(d / "cal.json"),
                 "--out", str(tmp_path / "a"), "--per-sweep", "--follow",
                 "--idle-timeout", "0.3", "--quiet"]) == 0  # fmt: skip
    assert len(ev.video.load_sweep_index(tmp_path / "a")["sweeps"]) == SWEEPS
    # the run's signal handlers are gone again (main() may run in-process)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    # SIGTERM while the writer is half-way: the sweeps read so far are finished
    live = tmp_path / "live.raw"
    writer = _writer(d / "rec.raw", live, speed=0.02)  # 20 s: time to stop it
    proc = subprocess.Popen(
        [sys.executable, "-m", "evhsi_jax.cli", "reconstruct", str(live), "--calib",
         str(d / "cal.json"), "--out", str(tmp_path / "b"), "--per-sweep", "--follow",
         "--idle-timeout", "30", "--quiet"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not (tmp_path / "b" / "sweep_000001.npz").exists():
            time.sleep(0.05)
        proc.terminate()
        _, err = proc.communicate(timeout=120)
    finally:
        writer.kill()
        writer.wait()
    assert proc.returncode == 0, err
    index = ev.video.load_sweep_index(tmp_path / "b")
    assert index["complete"] and 2 <= len(index["sweeps"]) < SWEEPS


def test_roi_equals_the_crop_of_the_full_cube(recording, tmp_path, capsys):
    d, cal = recording
    roi = (1, 1, 5, 3)
    res = ev.reconstruct_sweeps(d / "rec.raw", cal, tmp_path / "roi", roi=roi,
                                preview=False, max_sweeps=3)  # fmt: skip
    assert (res.index["height"], res.index["width"]) == (2, 4)
    for (_, full), (_, part) in zip(ev.video.iter_sweep_cubes(d / "offline"),
                                    ev.video.iter_sweep_cubes(tmp_path / "roi")):  # fmt: skip
        np.testing.assert_allclose(part["cube"], full["cube"][1:3, 1:5], atol=1e-5)
    assert main(["reconstruct", str(d / "rec.raw"), "--calib", str(d / "cal.json"),
                 "--out", str(tmp_path / "c.npz"), "--roi", "1,1,5,3", "--quiet"]) == 0
    assert ev.load_cube(tmp_path / "c.npz")["cube"].shape[:2] == (2, 4)
    capsys.readouterr()
    assert main(["reconstruct", str(d / "rec.raw"), "--calib", str(d / "cal.json"),
                 "--out", str(tmp_path / "c.npz"), "--roi", "1,1,9,3"]) == 2
    assert "not inside" in capsys.readouterr().err


def test_follow_waits_for_the_recording_to_appear(recording, tmp_path):
    """`--follow` started before the recorder: it waits (up to the idle timeout) for
    the file instead of failing with "not found"."""
    import shutil
    import threading

    d, cal = recording
    live = tmp_path / "late.raw"
    late = threading.Timer(0.5, shutil.copyfile, (d / "rec.raw", live))
    late.start()
    try:
        res = ev.reconstruct_sweeps(
            live, cal, tmp_path / "out", follow=True, idle_timeout_s=3.0,
            preview=False,
        )  # fmt: skip
    finally:
        late.join()
    assert res.reconstructed == SWEEPS
