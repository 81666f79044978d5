"""Each sweep's mirror speed measured from its own events: the estimate against the
truth, and what it gains (a design study on the training scene).

Setup: `tcs` (the training scene; never the evaluation scenes), `--size` (48×72), the
sensor's true rig and per-pixel thresholds (no calibration: this is where the
estimator's design was chosen; the held-out, calibrated figures are
`experiments/realism.py`'s). For each sensor and draw (`--seeds`), one recording of
`--sweeps` sweeps is reconstructed with `sweep_speed="off"` (the rig's speed), with
the estimate (`reconstruct`'s own: one sweep alone, several each in a window with the
sweep before) and with the true factors. The
sensors' noise keys are the reconstruction's noise model; the mirror-speed jitter alone
gets threshold noise 0.0033 in it (what a calibration read from such a chart at one
speed; since it reads each chart sweep at its own, ~0.0001: `chart_speed.py`).
`results/sweep_speed_4sweeps.json` was written before `reconstruct` estimated
recordings of several sweeps, by the same windows called directly (unscreened lists).

Prints a table (true and estimated deviation of each sweep, SAM / PSNR of the three)
and writes `--out` (JSON).

    .venv/bin/python experiments/sweep_speed.py [--sweeps 1] [--seeds 0,1,2,3]
        [--size 48x72] [--out experiments/results/sweep_speed.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev

SENSORS = {
    "mirror jitter 0.2 %": {"sweep_rate_jitter": 0.002},
    "mirror jitter 0.3 % + threshold noise 0.01": {
        "sweep_rate_jitter": 0.003,
        "threshold_noise": 0.01,
    },
    "threshold noise 0.01 (no mirror jitter)": {"threshold_noise": 0.01},
    "realistic preset": {"sensor": "realistic"},
}


def estimate(events, rig, info):
    """`reconstruct`'s estimate (one sweep alone; several each with the sweep
    before)."""
    _, inf = ev.reconstruct(events, rig, threshold_on_map=info.threshold_on,
                            threshold_off_map=info.threshold_off, return_info=True)  # fmt: skip
    return inf.sweep_speed


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="48x72")
    ap.add_argument("--sweeps", type=int, default=1)
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--out", default="experiments/results/sweep_speed.json")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    scene = ev.load_scene("tcs", (h, w))
    rows = []
    print(f"tcs {h}x{w}, {args.sweeps} sweep(s), true rig and thresholds; deviation "
          "f - 1 in 1e-3; SAM° / PSNR dB")  # fmt: skip
    print("| sensor | seed | true | estimated | off | estimate | true factors |")
    print("|---|---:|---|---|---:|---:|---:|")
    for name, keys in SENSORS.items():
        sim = ev.Rig.from_dict(keys)
        model = dict(keys)
        if set(keys) == {"sweep_rate_jitter"}:
            model["threshold_noise"] = 0.0033
        rig = ev.Rig.from_dict(model)
        truth = scene.truth_cube(rig.grid)
        for seed in (int(s) for s in args.seeds.split(",")):
            events, info = ev.simulate(scene, sim, sweeps=args.sweeps, key=jr.key(seed),
                                       return_info=True)  # fmt: skip
            est = estimate(events, rig, info)
            true = np.asarray(info.speed_factor, np.float64)
            res = {}
            for label, mode in (("off", "off"), ("estimate", est), ("true", true)):
                cube = ev.reconstruct(events, rig, threshold_on_map=info.threshold_on,
                                      threshold_off_map=info.threshold_off,
                                      sweep_speed=mode)  # fmt: skip
                m = ev.evaluate(cube, truth)
                res[label] = {"sam_deg": m["sam_deg"], "psnr_db": m["psnr_db"]}
            rows.append({"sensor": name, "seed": seed, "true": true.tolist(),
                         "estimated": np.asarray(est).tolist(), **res})  # fmt: skip

            def dev(f):
                return ", ".join(f"{1e3 * (v - 1):+.2f}" for v in f)

            print(f"| {name} | {seed} | {dev(true)} | {dev(est)} | "
                  + " | ".join(f"{res[k]['sam_deg']:.2f} / {res[k]['psnr_db']:.2f}"
                               for k in ("off", "estimate", "true")) + " |",
                  flush=True)  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.out).with_suffix(".tmp")
    tmp.write_text(json.dumps({"size": [h, w], "sweeps": args.sweeps, "rows": rows},
                              indent=1))  # fmt: skip
    tmp.replace(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
