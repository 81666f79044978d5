"""Channels study: how many channels a reconstruction needs — speed against error.

The paper's rig and this project's default recover M = 72 channels of 5 nm under a
band of 17.5 nm FWHM: the channels are narrower than the band that measures them, and
each pixel's QP has 72 unknowns. `reconstruct --channels N` (`Calibration.
with_channels`) recovers N channels over the same 400–760 nm instead. This study
measures what that costs in accuracy and gains in speed.

Accuracy (a user's procedure, as experiments/realism.py): for each sensor, a gray-chart
capture of 32 sweeps, `ev.calibrate` from the default rig plus what a user knows (the
preset's band profile), then three held-out scenes (`colorchecker`, `rainbow`,
`metamers`; the reconstruction's weights were tuned on `tcs`) simulated with the same
sensor, one sweep each, reconstructed with the calibration on N channels. The N-channel
cube is interpolated linearly between channel centres onto the 72 channel centres
(`ev.forward.resample_matrix`, as `evhsi evaluate --resample`) and compared with the
72-channel truth. "floor": the truth itself averaged into the N channels and
interpolated back the same way — the error of N channels with perfect data.

Speed: a 192×288 ColorChecker sweep of each sensor reconstructed with the true rig and
the sensor's per-pixel thresholds (timing only: its accuracy is not the table's), the
default backend (fused on a CPU, every core), medians of `--repeats` warm calls in one
process, with the same run's float32 matmul GFLOP/s.

Sensors: `ideal` (no effects) and the `realistic` preset (threshold noise 0.01, 5 µs
jitter, 10 kHz photoreceptor, 1 Hz noise events, 0.1 % hot pixels, ON/OFF correlation
0.5, 40 µs latency, 0.5 px PSF, skewed band, 3 nm sweep curvature, 0.2 % rate jitter).

Run: `.venv/bin/python experiments/channels.py [--quick]`
→ experiments/results/channels.json. Machine: the 2-core CI VM.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax.random as jr
import numpy as np
from _common import OUT, matmul_gflops, median_time, write_json
from realism import CHART_SWEEPS, user_init

import evhsi_jax as ev

SENSORS = {"ideal": {}, "realistic": {"sensor": "realistic"}}
SCENES = ("colorchecker", "rainbow", "metamers")  # held out (weights tuned on tcs)
CHANNELS = (72, 60, 48, 36, 30, 24)


def to_grid(cube, wl_from, wl_to):
    """`cube` (..., N) sampled at the channel centres `wl_from`, linearly interpolated
    onto `wl_to` (the metric's grid)."""
    w = ev.forward.resample_matrix(wl_from, wl_to)
    return np.asarray(cube, np.float64) @ w.T


def accuracy(name, keys, size, seed, channels) -> dict:
    h, w = size
    true = ev.Rig.from_dict(keys)
    key = jr.key(seed)
    chart = ev.load_scene("gray-chart", (h, w))
    gray = ev.simulate(chart, true, sweeps=CHART_SWEEPS, key=key)
    t0 = time.perf_counter()
    cal = ev.calibrate(gray, chart, user_init(true)).calibration
    out = {"calibration_s": time.perf_counter() - t0, "scenes": {}}
    wl72 = true.wavelengths_nm
    for scene_name in SCENES:
        scene = ev.load_scene(scene_name, (h, w))
        truth = scene.truth_cube(true.grid)
        events = ev.simulate(scene, true, sweeps=1, key=key)
        rows = {}
        for m in channels:
            c = cal.with_channels(m)
            cube = ev.reconstruct(events, c)
            got = ev.evaluate(to_grid(cube, c.rig.wavelengths_nm, wl72), truth)
            floor = to_grid(scene.truth_cube(c.rig.grid), c.rig.wavelengths_nm, wl72)
            best = ev.evaluate(floor, truth)
            rows[m] = {
                "sam_deg": got["sam_deg"],
                "psnr_db": got["psnr_db"],
                "floor_sam_deg": best["sam_deg"],
                "floor_psnr_db": best["psnr_db"],
            }
            print(
                f"{name:10s} {scene_name:12s} M={m:3d}  SAM {got['sam_deg']:6.3f}°  "
                f"PSNR {got['psnr_db']:6.2f} dB   (floor {best['sam_deg']:.3f}° / "
                f"{best['psnr_db']:.2f} dB)",
                flush=True,
            )
        out["scenes"][scene_name] = rows
    return out


def speed(name, keys, size, channels, repeats) -> dict:
    true = ev.Rig.from_dict(keys)
    scene = ev.load_scene("colorchecker", size)
    events, info = ev.simulate(
        scene, true, sweeps=1, key=jr.key(1), return_info=True
    )
    cal = ev.Calibration(true, info.threshold_on, info.threshold_off)
    n = size[0] * size[1]
    rows = {}
    for m in channels:
        c = cal.with_channels(m)
        s = median_time(lambda c=c: ev.reconstruct(events, c), repeats)
        rows[m] = {"seconds": s, "px_per_s": n / s}
        print(f"{name:10s} speed M={m:3d}  {s:.3f} s  {n / s:,.0f} px/s", flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="32x48", help="accuracy captures (HxW)")
    ap.add_argument("--speed-size", default="192x288", help="timing capture (HxW)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="72, 48 and 36 channels only")
    ap.add_argument("--out", default=str(OUT / "channels.json"))
    ap.add_argument("--table", metavar="JSON", help="print the tables of a finished run")
    args = ap.parse_args(argv)
    if args.table:
        print(markdown(json.loads(Path(args.table).read_text())))
        return
    ev.enable_compilation_cache()
    size = ev.forward.parse_size(args.size)
    speed_size = ev.forward.parse_size(args.speed_size)
    channels = (72, 48, 36) if args.quick else CHANNELS
    report = {
        "size": list(size),
        "speed_size": list(speed_size),
        "seed": args.seed,
        "chart_sweeps": CHART_SWEEPS,
        "matmul_gflops_f32": matmul_gflops(),
        "sensors": {},
    }
    for name, keys in SENSORS.items():
        report["sensors"][name] = {
            "accuracy": accuracy(name, keys, size, args.seed, channels),
            "speed": speed(name, keys, speed_size, channels, args.repeats),
        }
    report["matmul_gflops_f32_after"] = matmul_gflops()
    write_json(args.out, report)
    print(markdown(report))


def markdown(report) -> str:
    lines = []
    sensors = report["sensors"]
    channels = [int(m) for m in next(iter(sensors.values()))["speed"]]
    head = "| sensor | scene | " + " | ".join(f"M = {m}" for m in channels) + " |"
    lines += [
        "SAM° / PSNR dB against the 72-channel truth (floor: the truth itself on M "
        "channels, interpolated back)",
        "",
        head,
        "|---|---|" + "---:|" * len(channels),
    ]
    for name, data in sensors.items():
        for scene, rows in data["accuracy"]["scenes"].items():
            cells = [
                f"{_row(rows, m)['sam_deg']:.2f} / {_row(rows, m)['psnr_db']:.2f}"
                for m in channels
            ]
            lines.append(f"| {name} | {scene} | " + " | ".join(cells) + " |")
    for scene in SCENES:
        rows = next(iter(sensors.values()))["accuracy"]["scenes"][scene]
        cells = [
            f"{_row(rows, m)['floor_sam_deg']:.2f} / {_row(rows, m)['floor_psnr_db']:.2f}"
            for m in channels
        ]
        lines.append(f"| floor | {scene} | " + " | ".join(cells) + " |")
    lines += ["", head.replace("scene", "size"), "|---|---|" + "---:|" * len(channels)]
    size = "×".join(str(v) for v in report["speed_size"])
    for name, data in sensors.items():
        cells = [
            f"{_row(data['speed'], m)['px_per_s']:,.0f} px/s" for m in channels
        ]
        lines.append(f"| {name} | {size} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _row(rows: dict, m: int) -> dict:
    """Row `m` of a table read back from JSON (string keys) or made in this run."""
    return rows[str(m)] if str(m) in rows else rows[m]


if __name__ == "__main__":
    main()
