"""Reliability: no command destroys an input, bad input is one line and exit 2, counted
problems are reported, per-sweep folders are locked and verified, real multi-process.

Each test here failed (or could not be written) before the fix it guards; the CLI runs
in-process (`main([...])`) where it can, so compiled shapes are shared.
"""

import dataclasses
import fcntl
import json
import os
import platform
import socket
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._io import DecodeReport, EventReader
from evhsi_jax._io._header import format_header
from evhsi_jax._reconstruct._pipeline import select_sweeps
from evhsi_jax._video._stream import LOCK_NAME
from evhsi_jax.cli import main

H, W = 4, 6
EVHSI = [sys.executable, "-m", "evhsi_jax.cli"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A 2-sweep ColorChecker capture (.npz and .raw), its truth, a plain calibration
    and the reference cube of the capture."""
    d = tmp_path_factory.mktemp("rel")
    rig = ev.Rig()
    events = ev.simulate(ev.load_scene("colorchecker", (H, W)), rig, sweeps=2,
                         key=jr.key(2))  # fmt: skip
    ev.write_events(d / "ev.npz", events)
    ev.write_events(d / "ev.raw", events)
    (d / "cal.json").write_text("{}")
    assert main(["reconstruct", str(d / "ev.npz"), "--calib", str(d / "cal.json"),
                 "--out", str(d / "ref.npz"), "--quiet"]) == 0  # fmt: skip
    return d, events


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(code, err, *needles):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err
    for n in needles:
        assert n in err, err


# --- no command writes over one of its inputs ------------------------------------------
def test_no_command_overwrites_its_input(files, capsys, tmp_path):
    d, _ = files
    ev_file = tmp_path / "ev.npz"
    ev_file.write_bytes((d / "ev.npz").read_bytes())
    before = ev_file.read_bytes()
    cal = d / "cal.json"
    cases = [
        ("reconstruct", ev_file, "--calib", cal, "--out", ev_file),
        ("reconstruct", ev_file, "--calib", cal, "--out", tmp_path / "c.npz",
         "--preview", tmp_path / "c.npz"),  # fmt: skip
        ("simulate", "--scene", "colorchecker", "--size", "4x6", "--out",
         tmp_path / "x.npz", "--truth", tmp_path / "x.npz"),  # fmt: skip
        ("convert", ev_file, tmp_path / "." / "ev.npz"),
        ("calibrate", ev_file, "--out", tmp_path / "cal.json", "--init",
         tmp_path / "cal.json"),  # fmt: skip
    ]
    (tmp_path / "cal.json").write_text("{}")
    for argv in cases:
        code, _, err = run(capsys, *argv)
        assert code == 2, (argv, err)
        assert len(err.strip().splitlines()) == 1
    # calibrate's maps file beside E.json is E_thresholds.npz: an input of that name
    maps_named = tmp_path / "E_thresholds.npz"
    maps_named.write_bytes(before)
    code, _, err = run(capsys, "calibrate", maps_named, "--out", tmp_path / "E.json")
    one_line_error(code, err, "maps file", "input")
    assert maps_named.read_bytes() == before
    # a hard link is the same file under another name
    os.link(ev_file, tmp_path / "link.npz")
    code, _, err = run(capsys, "reconstruct", ev_file, "--calib", cal, "--out",
                       tmp_path / "link.npz")  # fmt: skip
    one_line_error(code, err, "input")
    assert ev_file.read_bytes() == before
    assert not (tmp_path / "x.npz").exists()


def test_a_reader_that_goes_away_is_not_an_error():
    """`evhsi rig | head -1`: stdout's reader closed before the command wrote. Not a
    fault of the input: no error line, the shell's code for SIGPIPE (141)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "evhsi_jax.cli", "rig"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # before the command has written anything
    with proc.stderr:
        err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert err == ""


def test_unwritable_output_is_found_before_any_work(files, capsys):
    d, _ = files
    t0 = time.perf_counter()
    code, _, err = run(capsys, "reconstruct", d / "ev.npz", "--calib", d / "cal.json",
                       "--out", "/proc/cube.npz")  # fmt: skip
    one_line_error(code, err, "cannot write into /proc")
    assert time.perf_counter() - t0 < 5  # no solve happened (loose: not a benchmark)


def test_cuda_backend_without_a_gpu_is_one_line(files, capsys, tmp_path):
    d, _ = files
    code, _, err = run(capsys, "reconstruct", d / "ev.npz", "--calib", d / "cal.json",
                       "--out", tmp_path / "c.npz", "--backend", "cuda")  # fmt: skip
    one_line_error(code, err, "cuda backend cannot run", "no CUDA GPU")
    assert not (tmp_path / "c.npz").exists()


# --- counted problems: reported, --strict makes them errors ----------------------------
def test_empty_first_sweep_does_not_poison_the_cube(files, capsys, tmp_path):
    d, events = files
    ref = ev.load_cube(d / "ref.npz")["cube"]
    period = round(float(ev.Rig().period_us))
    cal = ev.Calibration(ev.Rig())
    cube, info = ev.reconstruct(events, cal, t_start_us=-period, return_info=True)
    assert info.first_sweep == 1 and info.sweeps == 2 and info.t_start_us == 0
    np.testing.assert_array_equal(cube, ref)
    argv = ("reconstruct", d / "ev.npz", "--calib", d / "cal.json", "--out",
            tmp_path / "c.npz", "--t-start-us", -period, "--quiet")  # fmt: skip
    code, _, err = run(capsys, *argv)
    assert code == 0 and "warning" in err and "first 1 sweep" in err
    np.testing.assert_array_equal(ev.load_cube(tmp_path / "c.npz")["cube"], ref)
    code, _, err = run(capsys, *argv, "--strict")
    one_line_error(code, err, "--strict")


def test_a_stray_timestamp_far_away_costs_nothing(files, capsys, tmp_path):
    d, events = files
    ref = ev.load_cube(d / "ref.npz")["cube"]
    for t_far in (10**9, 2**62):
        far = dataclasses.replace(
            events,
            x=np.append(events.x, 1), y=np.append(events.y, 1),
            p=np.append(events.p, 1), t_us=np.append(events.t_us, t_far),
        )  # fmt: skip
        ev.write_events(tmp_path / "far.npz", far)
        code, _, err = run(capsys, "reconstruct", tmp_path / "far.npz", "--calib",
                           d / "cal.json", "--out", tmp_path / "c.npz", "--quiet")  # fmt: skip
        assert code == 0 and "1 sweep(s) with too few events" in err, err
        np.testing.assert_array_equal(ev.load_cube(tmp_path / "c.npz")["cube"], ref)


def test_select_sweeps():
    p = 100.0
    t = np.array([5, 10, 150, 160, 250, 260, 270], np.int64)  # sweeps 0, 1, 2
    assert select_sweeps(t, 0, p) == (0, 3, 0)
    assert select_sweeps(t, -100, p) == (1, 3, 0)  # one empty sweep first
    gap = np.array([5, 6, 7, 105, 106, 107, 905, 906, 907, 1005, 1006, 1007, 1105,
                    1106, 1107], np.int64)  # fmt: skip
    assert select_sweeps(gap, 0, p) == (9, 3, 2)  # the longest lit run wins
    dim = np.array([5, 105, 106, 107, 205, 206, 207], np.int64)
    assert select_sweeps(dim, 0, p) == (1, 2, 1)  # a sweep far below the median
    assert select_sweeps(np.arange(0, 3200, 50, dtype=np.int64), 0, p, max_sweeps=4)[
        1
    ] == 4


def test_select_sweeps_boundaries_match_the_per_event_sweep_index():
    # select_sweeps finds each sweep's first event by binary search; the sweeps and
    # their counts must be those of floor((t - t0) / P) of every event, also with
    # events exactly on a boundary, repeated timestamps and negative sweeps.
    rng = np.random.default_rng(0)
    for _ in range(200):
        p, t0 = rng.uniform(100, 5000), int(rng.integers(-5000, 5000))
        t = rng.integers(t0 - int(3 * p), t0 + int(rng.integers(1, 40) * p),
                         int(rng.integers(1, 2000)))  # fmt: skip
        t = np.repeat(t, rng.integers(1, 4, t.size))
        t = np.sort(np.concatenate([t, np.floor(t0 + np.arange(-2, 8) * p)])).astype(
            np.int64
        )
        k = np.floor((t - t0) / float(p)).astype(np.int64)
        ks, counts = np.unique(k, return_counts=True)
        lit = counts >= 0.5 * np.median(counts)
        runs = []  # (length, -first index) of each run of consecutive lit sweeps
        i = 0
        while i < ks.size:
            j = i
            while lit[i] and j + 1 < ks.size and lit[j + 1] and ks[j + 1] == ks[j] + 1:
                j += 1
            if lit[i]:
                runs.append((j - i + 1, -i))
            i = j + 1
        n, first = max(runs)
        n = min(n, 32)
        assert select_sweeps(t, t0, p) == (int(ks[-first]), n, ks.size - n)


def _raw_with_header(src: Path, dst: Path, width: int, height: int, data=b""):
    reader = EventReader(src)
    body = src.read_bytes()[reader.data_offset :]
    dst.write_bytes(format_header("evt3", width, height, None) + body + data)


def test_out_of_geometry_events_are_reported(files, capsys, tmp_path):
    d, _ = files
    small = tmp_path / "small.raw"
    _raw_with_header(d / "ev.raw", small, W // 2, H)
    code, _, err = run(capsys, "info", small)
    assert code == 0 and "warning" in err and "out of geometry skipped" in err
    code, _, err = run(capsys, "info", small, "--strict")
    one_line_error(code, err, "small.raw")


def test_time_jumping_back_is_an_error_for_computations(files, capsys, tmp_path):
    d, _ = files
    reader = EventReader(d / "ev.raw")
    body = (d / "ev.raw").read_bytes()[reader.data_offset :]
    cat = tmp_path / "cat.raw"
    _raw_with_header(d / "ev.raw", cat, W, H, data=body)  # the recording twice
    report = EventReader(cat)
    report.read()
    assert report.report.time_jumped_back
    code, _, err = run(capsys, "info", cat)
    assert code == 0 and "time jumps back" in err
    code, _, err = run(capsys, "reconstruct", cat, "--calib", d / "cal.json",
                       "--out", tmp_path / "c.npz")  # fmt: skip
    one_line_error(code, err, "time jumps back")
    assert not (tmp_path / "c.npz").exists()
    assert not DecodeReport(time_clamped=3, max_step_back_us=40).problems()  # quirk


def test_render_refuses_an_all_nan_cube_and_reports_inf(capsys, tmp_path):
    wl = np.linspace(400, 700, 8)
    ev.save_cube(tmp_path / "nan.npz", np.full((3, 4, 8), np.nan), wl)
    code, _, err = run(capsys, "render", tmp_path / "nan.npz", "--out", tmp_path / "a.png")
    one_line_error(code, err, "no pixel has a finite spectrum")
    assert not (tmp_path / "a.png").exists()
    cube = np.full((3, 4, 8), 0.5)
    cube[0, 0, 3] = np.inf
    ev.save_cube(tmp_path / "inf.npz", cube, wl)
    code, _, err = run(capsys, "render", tmp_path / "inf.npz", "--out", tmp_path / "b.png")
    assert code == 0 and err.count("\n") == 1 and "1 pixel(s) with NaN/inf" in err
    code, _, err = run(capsys, "evaluate", tmp_path / "inf.npz", "--truth",
                       tmp_path / "nan.npz")  # fmt: skip
    one_line_error(code, err, "inf.npz", "NaN/inf")


# --- sizes and corrupt files ------------------------------------------------------------
@pytest.mark.parametrize(
    "rig",
    [{"channels": 1e9}, {"fine_step_nm": 1e-7}, {"samples_per_sweep": 1e12},
     {"channels": 0}],  # fmt: skip
)
def test_absurd_rig_sizes_are_refused_up_front(rig, capsys, tmp_path):
    (tmp_path / "r.json").write_text(json.dumps(rig))
    code, _, err = run(capsys, "rig", "--rig", tmp_path / "r.json")
    one_line_error(code, err, next(iter(rig)))


def test_absurd_run_sizes_are_refused_up_front(capsys, tmp_path):
    code, _, err = run(capsys, "simulate", "--scene", "colorchecker", "--size", "4x6",
                       "--sweeps", 10**12, "--out", tmp_path / "e.npz")  # fmt: skip
    one_line_error(code, err, "memory")
    huge = ev.EventStream(x=[0, 1], y=[0, 1], p=[1, 0], t_us=[5, 9], width=65535,
                          height=65535)  # fmt: skip
    ev.write_events(tmp_path / "huge.npz", huge)
    (tmp_path / "cal.json").write_text("{}")
    code, _, err = run(capsys, "reconstruct", tmp_path / "huge.npz", "--calib",
                       tmp_path / "cal.json", "--out", tmp_path / "c.npz")  # fmt: skip
    one_line_error(code, err, "65535x65535", "memory")


def _flip(path: Path, where: float) -> None:
    data = bytearray(path.read_bytes())
    i = int(len(data) * where)
    data[i] ^= 0x5A
    path.write_bytes(bytes(data))


def test_corrupt_user_files_are_named(files, capsys, tmp_path):
    d, _ = files
    src = (d / "ev.npz").read_bytes()
    bad = {}
    bad["truncated.npz"] = src[: len(src) // 2]
    bad["empty.npz"] = b""
    p = tmp_path / "flipped.npz"
    p.write_bytes(src)
    with zipfile.ZipFile(p) as z:  # flip a byte inside the t_us member's data
        info = z.getinfo("t_us.npy")
    data = bytearray(src)
    data[info.header_offset + 30 + len(info.filename) + 200] ^= 0xFF
    bad["flipped.npz"] = bytes(data)
    np.save(tmp_path / "arr.npy", np.arange(4))
    bad["renamed.npz"] = (tmp_path / "arr.npy").read_bytes()
    for name, blob in bad.items():
        (tmp_path / name).write_bytes(blob)
    ev_np = dict(np.load(d / "ev.npz"))
    np.savez(tmp_path / "width_array.npz", **{**ev_np, "width": np.array([6, 6])})
    for name in [*bad, "width_array.npz"]:
        for argv in (("info", tmp_path / name),
                     ("reconstruct", tmp_path / name, "--calib", d / "cal.json",
                      "--out", tmp_path / "c.npz")):  # fmt: skip
            code, _, err = run(capsys, *argv)
            one_line_error(code, err, name)
    # a damaged threshold-map file named by a calibration
    (tmp_path / "c_thresholds.npz").write_bytes(src[:100])
    (tmp_path / "c.json").write_text(json.dumps({"threshold_map": "c_thresholds.npz"}))
    code, _, err = run(capsys, "reconstruct", d / "ev.npz", "--calib",
                       tmp_path / "c.json", "--out", tmp_path / "c.npz")  # fmt: skip
    one_line_error(code, err, "c_thresholds.npz")


def test_cli_fuzz(files, capsys, tmp_path):
    """Random damage to every kind of input file: exit 0 or one line and exit 2."""
    d, _ = files
    rng = np.random.default_rng(7)
    wl = np.linspace(400, 700, 6)
    ev.save_cube(tmp_path / "cube.npz", np.full((H, W, 6), 0.4), wl)
    sources = {
        "ev.npz": (d / "ev.npz").read_bytes(),
        "ev.raw": (d / "ev.raw").read_bytes(),
        "cube.npz": (tmp_path / "cube.npz").read_bytes(),
        "rig.json": json.dumps({"channels": 16, "fwhm_nm": 20.0}).encode(),
    }
    commands = {
        "ev.npz": lambda f: ("info", f),
        "ev.raw": lambda f: ("convert", f, tmp_path / "o.npz"),
        "cube.npz": lambda f: ("render", f, "--out", tmp_path / "o.png"),
        "rig.json": lambda f: ("rig", "--rig", f, "--size", "4x6"),
    }
    for i in range(48):
        name = list(sources)[i % len(sources)]
        blob = bytearray(sources[name])
        kind = rng.integers(3)
        if kind == 0:  # flip bytes
            for j in rng.integers(0, len(blob), size=rng.integers(1, 6)):
                blob[j] ^= int(rng.integers(1, 256))
        elif kind == 1:  # truncate
            blob = blob[: int(rng.integers(0, len(blob)))]
        else:  # splice in junk
            j = int(rng.integers(0, len(blob)))
            blob[j:j] = rng.integers(0, 256, size=int(rng.integers(1, 64))).astype(
                np.uint8
            ).tobytes()
        f = tmp_path / f"fuzz{i}_{name}"
        f.write_bytes(bytes(blob))
        code, _, err = run(capsys, *commands[name](f))
        assert code in (0, 2), (name, kind, err)
        if code == 2:
            one_line_error(code, err)
        else:
            assert "Traceback" not in err


# --- per-sweep folders: locked, verified, cleaned ---------------------------------------
def test_per_sweep_folder_is_locked_verified_and_cleaned(files, tmp_path):
    d, events = files
    out = tmp_path / "video"
    cal = ev.Calibration(ev.Rig())
    res = ev.reconstruct_sweeps(events, cal, out, preview=False)
    assert res.reconstructed == 2
    index = ev.video.load_sweep_index(out)
    assert all(len(e["sha256"]) == 64 for e in index["sweeps"])
    # a second run while the folder is locked is refused
    fd = os.open(out / LOCK_NAME, os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        with pytest.raises(ValueError, match="in use by another evhsi run"):
            ev.reconstruct_sweeps(events, cal, out, overwrite=True, preview=False)
    finally:
        os.close(fd)
    # a bit flipped in a finished file: the resume redoes that sweep
    good = (out / "sweep_000000.npz").read_bytes()
    _flip(out / "sweep_000000.npz", 0.5)
    (out / ".sweep_000001.npz.k1ll3d.tmp").write_bytes(b"half a file")
    res = ev.reconstruct_sweeps(events, cal, out, preview=False)
    assert (res.reconstructed, res.skipped, res.stale_removed) == (1, 1, 1)
    assert (out / "sweep_000000.npz").read_bytes() == good
    assert not list(out.glob(".*.tmp"))


def test_two_per_sweep_runs_into_one_folder(files, tmp_path):
    """The issue's case: a second CLI run into the folder of a running one refuses."""
    d, _ = files
    out = tmp_path / "video"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDWR | "
         "os.O_CREAT); fcntl.flock(fd, fcntl.LOCK_EX); os.write(fd, b'4242'); "
         "print('locked', flush=True); time.sleep(60)", str(out / LOCK_NAME)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "locked"
        proc = subprocess.run(
            [*EVHSI, "reconstruct", d / "ev.raw", "--calib", d / "cal.json", "--out",
             out, "--per-sweep", "--restart", "--quiet"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    assert proc.returncode == 2, proc.stderr
    assert "in use by another evhsi run (pid 4242)" in proc.stderr
    assert not list(out.glob("sweep_*"))


# --- multi-process -----------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(port, pid, n=2, timeout=120):
    return {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "EVHSI_COORDINATOR": f"127.0.0.1:{port}",
        "EVHSI_NUM_PROCESSES": str(n),
        "EVHSI_PROCESS_ID": str(pid),
        "EVHSI_DISTRIBUTED_TIMEOUT": str(timeout),
    }


def test_unreachable_coordinator_times_out_with_one_line(files):
    d, _ = files
    port = _free_port()
    for pid in (1, 0):  # a worker finds no coordinator; the coordinator no worker
        t0 = time.perf_counter()
        proc = subprocess.run(
            [*EVHSI, "--distributed", "info", d / "ev.npz"],
            env=_env(port, pid, timeout=3), capture_output=True, text=True, timeout=90,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert f"127.0.0.1:{port}" in proc.stderr and "within 3 s" in proc.stderr
        assert time.perf_counter() - t0 < 80


def test_two_process_distributed_reconstruction_equals_one_process(files, tmp_path):
    d, _ = files
    port = _free_port()
    procs = [
        subprocess.Popen(
            [*EVHSI, "--distributed", "reconstruct", d / "ev.npz", "--calib",
             d / "cal.json", "--out", tmp_path / "dist.npz", "--devices", "0",
             "--quiet"],
            env=_env(port, pid), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for pid in (0, 1)
    ]
    outs = [p.communicate(timeout=400) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    one = ev.load_cube(d / "ref.npz")["cube"]
    two = ev.load_cube(tmp_path / "dist.npz")["cube"]
    # Each process solves half the pixels; XLA compiles the two-device kernel apart
    # from the one-device one (see test_shard), so float32 rounding differs.
    np.testing.assert_allclose(two, one, rtol=0, atol=2e-4)
    assert not np.array_equal(two, np.zeros_like(two))


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
    reason="malloc_trim is glibc's (elsewhere release_free_memory does nothing)",
)
def test_release_free_memory_hands_back_the_heaps_free_pages():
    """Memory freed inside glibc's heap (blocks below its mmap threshold, kept
    from the top of the heap by small live blocks, as the compiler's leftovers are)
    stays resident until `release_free_memory` trims it: the calibration calls it
    before its threshold maps."""
    from evhsi_jax._base import release_free_memory

    def rss_mb():
        with open("/proc/self/status") as f:
            return int(f.read().split("VmRSS:")[1].split()[0]) / 1024

    big, pins = [], []
    for _ in range(2000):  # 2000 × 100 kB, each followed by a small live block
        a = np.empty(100_000 // 8)
        a[:] = 1.0
        big.append(a)
        pins.append(np.ones(4))
    del big
    held = rss_mb()
    assert release_free_memory() is True
    assert rss_mb() < held - 100  # most of the 200 MB handed back
    assert len(pins) == 2000
