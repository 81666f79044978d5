"""Time and memory of `evhsi calibrate` at a given sensor size.

Simulates a 2-sweep gray-chart capture of `--height` × `--width` pixels from
`true_rig.json` (with `config.json`'s column-offset wiggle and camera tilt) and writes
it to a temporary folder; then runs `evhsi calibrate` on it from the paper rig (global fit +
per-pixel threshold maps) in its own process, as a user does, `--repeats` times with
one compilation cache folder (the first run fills it: that run includes compilation;
the others start warm). Reports each run's wall time and peak resident memory (the
calibrating process alone, not the simulation) and its CPU seconds (user + system;
less sensitive than the wall time to what else the machine runs), the
Levenberg–Marquardt steps and the parameter errors against the truth, with the same
machine's float32 matmul GFLOP/s.
Writes `calib/out/bench_calibration_<H>x<W>.json`.

`--sensor realistic`: the capture from a sensor with the `realistic` preset's effects
on (threshold noise, jitter, a 10 kHz photoreceptor, noise events, hot pixels, ON/OFF
correlation, latency, a 0.5 px PSF, a skewed band, sweep curvature, rate jitter), and
`evhsi calibrate --init` given what such a user knows of the hardware (the band
profile, as `experiments/realism.py`; the photoreceptor cut-off is measured, since
2026-11-28): the path a real rig's calibration takes (the chart's traces through the
low-pass, the noise and PSF measurements). Writes `..._realistic.json`.

Run: `.venv/bin/python calib/bench_calibration.py --width 1280` (~4 min on 2 cores);
`--height 720 --width 1280` for a full sensor (~10 min, ~40 M events).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax.random as jr
from run_calibration import rms, true_rig, true_values

import evhsi_jax as ev

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "experiments"))
from _common import matmul_gflops  # noqa: E402  (the studies' one copy)


def run_cli(events_path: Path, out: Path, cache: Path, rows: int, init=None) -> dict:
    """One `evhsi calibrate` process: wall time and its peak resident memory."""
    env = {**os.environ, "EVHSI_CACHE_DIR": str(cache)}
    cmd = [sys.executable, "-m", "evhsi_jax.cli", "calibrate", str(events_path),
           "--chart", "gray-chart", "--out", str(out), "--rows-per-patch", str(rows)]  # fmt: skip
    if init is not None:
        cmd += ["--init", str(init)]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own peak memory
        wall = time.perf_counter() - t0
        if os.waitstatus_to_exitcode(status) != 0:
            err.seek(0)
            raise SystemExit(f"evhsi calibrate failed: {err.read().strip()[-400:]}")
    # CPU seconds too: on a shared machine they vary less than the wall time
    cpu = usage.ru_utime + usage.ru_stime
    return {"seconds": wall, "cpu_s": cpu, "peak_rss_mb": usage.ru_maxrss / 1024}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--rows-per-patch", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", default=None, help="result file (default: calib/out/...)")
    ap.add_argument("--sensor", default="ideal", choices=["ideal", "realistic"])
    ap.add_argument(
        "--new-capture", action="store_true",
        help="then calibrate a second capture of the chart (another seed) with the "
        "cache the runs filled: a user's next calibration of the same rig",
    )  # fmt: skip
    args = ap.parse_args()
    cfg = json.loads((HERE / "config.json").read_text())
    h, w = args.height, args.width
    truth = true_rig(cfg, w, HERE)
    init = None
    if args.sensor == "realistic":
        from evhsi_jax._model._rig import SENSOR_PRESETS

        truth = ev.Rig.from_dict({**truth.to_dict(), **SENSOR_PRESETS["realistic"]})
        init = {  # what the user knows: the band profile (the cut-off is measured)
            "band_profile": {
                "offset_nm": [float(v) for v in truth.band_profile[0]],
                "values": [float(v) for v in truth.band_profile[1]],
            },
        }
    chart = ev.load_scene("gray-chart", (h, w))
    t0 = time.perf_counter()
    events, sim = ev.simulate(chart, truth, sweeps=2, key=jr.key(3), return_info=True)
    sim_s = time.perf_counter() - t0
    outdir = HERE / "out"
    outdir.mkdir(parents=True, exist_ok=True)
    gflops = matmul_gflops()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        events_path = Path(tmp) / "chart.npz"
        ev.write_events(events_path, events)
        cache, cal_path = Path(tmp) / "cache", Path(tmp) / "calib.json"
        init_path = None
        if init is not None:
            init_path = Path(tmp) / "init.json"
            init_path.write_text(json.dumps(init))
        for _ in range(args.repeats):
            runs.append(
                run_cli(events_path, cal_path, cache, args.rows_per_patch, init_path)
            )
            print(runs[-1], flush=True)
        cal = ev.load_calibration(cal_path)
        new = None
        if args.new_capture:
            again = ev.simulate(chart, truth, sweeps=2, key=jr.key(4))
            again_path = Path(tmp) / "chart2.npz"
            ev.write_events(again_path, again)
            new = run_cli(again_path, Path(tmp) / "calib2.json", cache,
                          args.rows_per_patch, init_path)  # fmt: skip
            print("new capture:", new, flush=True)
    rig = cal.rig
    report = cal.report
    true_vals = true_values(truth, sim)
    out = {
        "command": f"python calib/bench_calibration.py --width {w} --height {h} "
        f"--rows-per-patch {args.rows_per_patch} --repeats {args.repeats} "
        f"--sensor {args.sensor}" + (" --new-capture" if args.new_capture else ""),
        "sensor": args.sensor,
        "size": [h, w],
        "events": len(events),
        "events_used": report.get("events_used"),
        "simulation_s": sim_s,
        "runs": runs,  # first: empty compilation cache; later: warm
        # another capture of the chart, with the cache the runs filled
        "new_capture_run": new,
        "steps": report.get("steps"),
        "matmul_gflops_f32": gflops,
        "error_pct": {
            k: 100 * (float(getattr(rig, k)) / v - 1) for k, v in true_vals.items()
        },
        "tau_rms_error_us": rms(rig.column_offsets_us, truth.column_offsets(w)),
        "threshold_map_rms": rms(cal.threshold_on, sim.threshold_on),
        "photoreceptor_hz": {
            "fitted": float(rig.effects.photoreceptor_hz),
            "true": float(truth.effects.photoreceptor_hz),
        },
    }
    suffix = "" if args.sensor == "ideal" else f"_{args.sensor}"
    path = Path(args.out) if args.out else outdir / f"bench_calibration_{h}x{w}{suffix}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
