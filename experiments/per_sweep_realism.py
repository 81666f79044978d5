"""Per-sweep (video) runs of a real sensor, calibrated as a user would: each sweep of
a held-out recording reconstructed on its own, its pixels' references carried from
the sweep before.

Setup (as `realism.py`): 32×48 sensor (`--seed` picks it: its threshold maps and
draws), a gray chart recorded for 32 sweeps → `ev.calibrate` from the default rig and
the band profile → the ColorChecker (held out, never tuned on) recorded for
`--sweeps` sweeps by the same sensor → `ev.reconstruct_sweeps` with the calibration
(all defaults). Sensors: the `realistic` preset (every effect), per-crossing threshold
noise 0.01 alone and mirror-speed jitter 0.2 % alone (each plus the per-pixel
threshold spread 0.01). Prints each sweep's SAM and the mean SAM / PSNR of the sweeps
after the first (those with a carried reference), and writes `--out`.

    .venv/bin/python experiments/per_sweep_realism.py [--sweeps 6] [--seed 7]
        [--out experiments/results/per_sweep_realism.json]

To compare with another tree: `git worktree add /tmp/old REV`, then the same command
with `PYTHONPATH=/tmp/old` (and another `--out`).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import jax.random as jr
import numpy as np
from realism import sensor_keys, user_init

import evhsi_jax as ev

SENSORS = {
    "realistic preset": {"sensor": "realistic"},
    "threshold noise 0.01": {"threshold_noise": 0.01},
    "mirror jitter 0.2 %": {"sweep_rate_jitter": 0.002},
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sweeps", type=int, default=6)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default="experiments/results/per_sweep_realism.json")
    args = ap.parse_args()
    h, w = 32, 48
    chart = ev.load_scene("gray-chart", (h, w))
    scene = ev.load_scene("colorchecker", (h, w))
    rows = []
    for name, keys in SENSORS.items():
        true = ev.Rig.from_dict(sensor_keys(keys))
        key = jr.key(args.seed)  # (the sensor: calibrated and recording alike)
        gray = ev.simulate(chart, true, sweeps=32, key=key)
        cal = ev.calibrate(gray, chart, user_init(true)).calibration
        events = ev.simulate(scene, true, sweeps=args.sweeps, key=key)
        truth = scene.truth_cube(true.grid)
        with tempfile.TemporaryDirectory() as d:
            res = ev.reconstruct_sweeps(events, cal, Path(d) / "o", preview=False)
            m = [ev.evaluate(c["cube"], truth)
                 for _, c in ev.video.iter_sweep_cubes(Path(d) / "o")]  # fmt: skip
            speeds = [e.get("sweep_speed") for e in res.index["sweeps"]]
        sam = [x["sam_deg"] for x in m]
        psnr = [x["psnr_db"] for x in m]
        row = {"sensor": name, "sam_deg": sam, "psnr_db": psnr, "sweep_speed": speeds,
               "later_sam_deg": float(np.mean(sam[1:])),
               "later_psnr_db": float(np.mean(psnr[1:]))}  # fmt: skip
        rows.append(row)
        print(f"{name}: SAM per sweep {', '.join(f'{v:.2f}' for v in sam)}; sweeps 2-"
              f"{len(sam)}: {row['later_sam_deg']:.2f}° / {row['later_psnr_db']:.2f} dB",
              flush=True)  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(args.out).with_suffix(".tmp")
    tmp.write_text(json.dumps({"size": [h, w], "sweeps": args.sweeps,
                               "seed": args.seed, "rows": rows}, indent=1))  # fmt: skip
    tmp.replace(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
