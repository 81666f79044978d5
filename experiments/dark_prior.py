"""The dark-channel prior: for which noise and how many sweeps does it help?

The prior ties each channel the lamp barely lights to its neighbour when the sensor
is noisy (`ProblemConfig.alpha_dark`). Until the twenty-fifth session every solve with
a noise model got it, whatever its length, each pixel's share counting timestamp
jitter as noise; since then (`_problem.dark_strength`) only solves of one sweep get
it (`dark_sweeps`), and a pixel's share is what threshold noise alone would take of
its rows' variance. This study is what that was chosen on: the training scene `tcs`
only (never the ColorChecker, which the realism study holds out), true rig and
threshold maps, each sensor's capture reconstructed with the default, without the
prior ("none"), at a third of its weight, and — where the tree has `dark_sweeps` — at
every length ("every length"). Run it on the tree before the change too (PYTHONPATH
of a worktree: its "default" is the old rule). Printed: mean SAM / PSNR over seeds.

    .venv/bin/python experiments/dark_prior.py [--seeds 1,2] [--size 32x48]
        [--out experiments/results/dark_prior.json]
    # ~6 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev
from evhsi_jax.reconstruction import ProblemConfig

#: (sensor keys, sweeps): threshold noise and timestamp jitter from one sweep, and
#: recordings of several.
CASES = [
    ({"threshold_noise": 0.0025}, 1),
    ({"threshold_noise": 0.005}, 1),
    ({"threshold_noise": 0.01}, 1),
    ({"threshold_noise": 0.02}, 1),
    ({"timestamp_jitter_us": 2.0}, 1),
    ({"timestamp_jitter_us": 5.0}, 1),
    ({"timestamp_jitter_us": 15.0}, 1),
    ({"sensor": "realistic"}, 1),
    ({"threshold_noise": 0.01}, 2),
    ({"threshold_noise": 0.01}, 4),
    ({"threshold_noise": 0.02}, 4),
    ({"timestamp_jitter_us": 5.0}, 4),
    ({"sensor": "realistic"}, 4),
]


def configs() -> dict[str, ProblemConfig]:
    out = {
        "default": ProblemConfig(),
        "none": ProblemConfig(alpha_dark=0.0),
        "third": ProblemConfig(alpha_dark=ProblemConfig().alpha_dark / 3),
    }
    if "dark_sweeps" in ProblemConfig.__dataclass_fields__:
        out["every length"] = ProblemConfig(dark_sweeps=1 << 20)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="32x48")
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    seeds = [int(v) for v in args.seeds.split(",")]
    scene = ev.load_scene("tcs", (h, w))
    cfgs = configs()
    rows = []
    print(f"evhsi_jax from {ev.__file__}; SAM° / PSNR dB")
    for keys, sweeps in CASES:
        rig = ev.Rig.from_dict(keys)
        truth = np.asarray(scene.truth_cube(rig.grid), np.float64)
        got = {name: [] for name in cfgs}
        for seed in seeds:
            events, info = ev.simulate(
                scene, rig, sweeps=sweeps, key=jr.key(seed), return_info=True
            )
            cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
            for name, cfg in cfgs.items():
                cube = ev.reconstruct(events, cal, sweep_speed="off", config=cfg)
                m = ev.evaluate(cube, truth)
                got[name].append([m["sam_deg"], m["psnr_db"]])
        mean = {k: np.mean(v, axis=0).tolist() for k, v in got.items()}
        rows.append({"sensor": keys, "sweeps": sweeps, "sam_psnr": mean})
        print(
            f"{json.dumps(keys):44s} {sweeps} sweep(s)  "
            + "  ".join(f"{k}: {v[0]:.2f}/{v[1]:.1f}" for k, v in mean.items()),
            flush=True,
        )
    if args.out:
        setup = {"scene": "tcs", "size": [h, w], "seeds": seeds,
                 "calibration": "true rig and threshold maps", "sweep_speed": "off",
                 "package": ev.__file__}  # fmt: skip
        Path(args.out).write_text(json.dumps({"setup": setup, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
