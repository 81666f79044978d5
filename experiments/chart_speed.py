"""The mirror's speed in the chart's sweeps: what reading each sweep of the gray chart
at its own speed gives a calibrated reconstruction (a design study on the training
scene).

Setup (a user's procedure): for each sensor and draw (`--seeds`), a 32-sweep gray
chart is calibrated twice from the default rig — as `evhsi calibrate` does now (each
sweep's speed measured from the chart, the chart fitted again at them when they differ
by more than the estimate's error: `_calibrate._chart.chart_sweep_speeds`) and with
one speed for every sweep (`sweep_speeds=None`, what it did before); then the training scene
`tcs` (never an evaluation scene) is recorded by the same sensor for 1 and 4 sweeps
and reconstructed with each calibration at the calibration's speed (`sweep_speed="off"`),
with `reconstruct`'s own estimate (`"auto"`: one sweep alone, several each with the
sweep before) and with the recording's true factors. The held-out figures are
`experiments/realism.py`'s.

Prints a table (SAM° per case) and writes `--out` (JSON).

    .venv/bin/python experiments/chart_speed.py [--seeds 1,2] [--size 32x48]
        [--sensors j1,j2,j5,j2tn,preset,tn,bg]
        [--out experiments/results/chart_speed.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax.random as jr
import numpy as np
from realism import sensor_keys, user_init

import evhsi_jax as ev

SENSORS = {
    "j1": {"sweep_rate_jitter": 0.001},
    "j2": {"sweep_rate_jitter": 0.002},
    "j5": {"sweep_rate_jitter": 0.005},
    "j2tn": {"sweep_rate_jitter": 0.002, "threshold_noise": 0.01},
    "preset": {"sensor": "realistic"},
    "tn": {"threshold_noise": 0.01},  # (controls: no mirror jitter)
    "bg": {"noise_rate_hz": 0.3},
}
CHART_SWEEPS = 32


def run_case(keys, size, seed) -> dict:
    chart = ev.load_scene("gray-chart", size)
    scene = ev.load_scene("tcs", size)
    true = ev.Rig.from_dict(sensor_keys(keys))
    key = jr.key(seed)
    gray, ginfo = ev.simulate(chart, true, sweeps=CHART_SWEEPS, key=key, return_info=True)
    out = {"chart_factors": np.asarray(ginfo.speed_factor).tolist()}
    cals = {}
    for name, kw in (("each", {}), ("one", {"sweep_speeds": None})):
        t0 = time.perf_counter()
        res = ev.calibrate(gray, chart, user_init(true), **kw)
        cals[name] = res.calibration
        out[f"{name}_calibration"] = {
            "seconds": time.perf_counter() - t0,
            "sweep_speed": res.sweep_speed_note,
            "sweep_rate_jitter": float(res.rig.effects.sweep_rate_jitter),
            "threshold_noise": float(res.rig.effects.threshold_noise),
            "measured": None if res.sweep_speeds is None
            else res.sweep_speeds.factors.tolist(),
        }  # fmt: skip
    for sweeps in (1, 4):
        events, info = ev.simulate(scene, true, sweeps=sweeps, key=key, return_info=True)
        truth = scene.truth_cube(true.grid)
        factors = np.asarray(info.speed_factor, np.float64)
        out[f"true_{sweeps}"] = factors.tolist()
        for name, cal in cals.items():
            for mode in ("off", "auto", "true"):
                cube, inf = ev.reconstruct(
                    events, cal, sweep_speed=factors if mode == "true" else mode,
                    return_info=True,
                )  # fmt: skip
                m = ev.evaluate(cube, truth)
                out[f"{name}_{sweeps}_{mode}"] = {
                    "sam_deg": m["sam_deg"], "psnr_db": m["psnr_db"],
                    "factors": None if inf.sweep_speed is None
                    else inf.sweep_speed.tolist(),
                }  # fmt: skip
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="32x48")
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--sensors", default=",".join(SENSORS))
    ap.add_argument("--out", default="experiments/results/chart_speed.json")
    args = ap.parse_args()
    size = ev.forward.parse_size(args.size)
    rows = []
    cols = [f"{c}_{s}_{m}" for s in (1, 4) for c in ("one", "each")
            for m in ("off", "auto", "true")]  # fmt: skip
    print(f"tcs {size[0]}x{size[1]}, calibrated from a {CHART_SWEEPS}-sweep chart; SAM°: "
          "calibration (one speed / each sweep's) _ sweeps _ reconstruction's speed")  # fmt: skip
    print("| sensor | seed | " + " | ".join(cols) + " |")
    print("|---|---:|" + "---:|" * len(cols))
    for name in args.sensors.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = run_case(SENSORS[name], size, seed)
            rows.append({"sensor": name, "keys": SENSORS[name], "seed": seed, **r})
            print(f"| {name} | {seed} | "
                  + " | ".join(f"{r[c]['sam_deg']:.2f}" for c in cols) + " |",
                  flush=True)  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.out).with_suffix(".tmp")
    tmp.write_text(json.dumps({"size": list(size), "chart_sweeps": CHART_SWEEPS,
                               "rows": rows}, indent=1))  # fmt: skip
    tmp.replace(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
