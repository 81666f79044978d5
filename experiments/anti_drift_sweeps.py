"""The anti-drift prior's weight over a recording of several sweeps.

`ProblemConfig.alpha_int` is the anti-drift prior's weight over the whole recording:
a recording of S sweeps gives each sweep's anti-drift rows alpha_int / S. Until
2026-11-29 every sweep had the whole weight, so the prior grew with the data and its
bias did not fall with more sweeps. This study compares the two on true maps (no
calibration error): "per sweep" (the old weighting, `alpha_int × S` passed so that
each sweep gets `alpha_int`) and "per recording" (the default now), for an ideal
sensor, per-crossing threshold noise 0.01 and the `realistic` preset, recorded for
1, 4 and 16 sweeps. The default scene is the training scene `tcs` (the weights'
choices are made there); `--scene colorchecker` gives the held-out one.

    .venv/bin/python experiments/anti_drift_sweeps.py [--scene tcs] [--size 32x48]
    # ~4 min on 2 cores; --out writes the rows as JSON
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.random as jr

import evhsi_jax as ev
from evhsi_jax.reconstruction import ProblemConfig

SENSORS = {
    "ideal": {},
    "threshold noise 0.01": {"threshold_noise": 0.01},
    "realistic preset": {"sensor": "realistic"},
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="tcs")
    ap.add_argument("--size", default="32x48")
    ap.add_argument("--sweeps", default="1,4,16")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    alpha = ProblemConfig().alpha_int
    rows = []
    for name, keys in SENSORS.items():
        rig = ev.Rig.from_dict(keys)
        scene = ev.load_scene(args.scene, (h, w))
        truth = scene.truth_cube(rig.grid)
        for sweeps in (int(v) for v in args.sweeps.split(",")):
            events, info = ev.simulate(
                scene, rig, sweeps=sweeps, key=jr.key(args.seed), return_info=True
            )
            cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
            row = {"sensor": name, "sweeps": sweeps}
            for label, a in (("per_sweep", alpha * sweeps), ("per_recording", alpha)):
                cube = ev.reconstruct(events, cal, config=ProblemConfig(alpha_int=a))
                m = ev.evaluate(cube, truth)
                row[label] = {"sam_deg": m["sam_deg"], "psnr_db": m["psnr_db"]}
            rows.append(row)
            a, b = row["per_sweep"], row["per_recording"]
            print(
                f"{name:22s} {sweeps:3d} sweeps  per sweep {a['sam_deg']:.2f}° "
                f"{a['psnr_db']:.2f} dB  per recording {b['sam_deg']:.2f}° "
                f"{b['psnr_db']:.2f} dB",
                flush=True,
            )
    if args.out:
        setup = {"scene": args.scene, "size": [h, w], "seed": args.seed,
                 "alpha_int": alpha, "calibration": "true rig and maps"}  # fmt: skip
        Path(args.out).write_text(json.dumps({"setup": setup, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
