"""Per-crossing threshold noise: does the error fall as a static recording grows?

A sensor with per-crossing threshold noise only (σ_C = 0.01 log units, plus the
default per-pixel threshold spread), the true rig and the true threshold maps given
to `reconstruct` (no calibration error), the ColorChecker recorded for 1, 4 and 16
sweeps (`--passes 0`: the first, linear solve alone, which has an errors-in-variables
bias: README Limitations, "Threshold noise leaves a bias"). With an unbiased
estimator the error would keep falling with the sweeps; a floor that stays says the
estimator is biased. Printed per recording: SAM / PSNR
against the truth and the mean error (reconstruction − truth, averaged over the
pixels) of every 8th channel, whose sign and size show the bias.

    .venv/bin/python experiments/threshold_noise_floor.py [--size 32x48] [--noise 0.01]
        [--passes 0]
    # ~2 min on 2 cores; --out writes the figures as JSON
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev
from evhsi_jax.reconstruction import ProblemConfig


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="32x48")
    ap.add_argument("--noise", type=float, default=0.01, help="σ_C, log units")
    ap.add_argument("--sweeps", default="1,4,16")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--backend", default="auto")
    ap.add_argument(
        "--passes",
        type=int,
        default=None,
        help="ProblemConfig.lowpass_passes (default its default; 0: the first, linear "
        "solve alone, which has the bias)",
    )
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    rig = ev.Rig.from_dict({"threshold_noise": args.noise})
    scene = ev.load_scene("colorchecker", (h, w))
    truth = np.asarray(scene.truth_cube(rig.grid), np.float64)
    centres = np.asarray(rig.grid.centres_nm)
    cfg = ProblemConfig() if args.passes is None else ProblemConfig(
        lowpass_passes=args.passes
    )
    rows = []
    for sweeps in (int(v) for v in args.sweeps.split(",")):
        events, info = ev.simulate(
            scene, rig, sweeps=sweeps, key=jr.key(args.seed), return_info=True
        )
        cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
        cube = ev.reconstruct(events, cal, backend=args.backend, config=cfg)
        m = ev.evaluate(cube, truth)
        bias = (np.asarray(cube, np.float64) - truth).mean(axis=(0, 1))
        rows.append({
            "sweeps": sweeps, "sam_deg": m["sam_deg"], "psnr_db": m["psnr_db"],
            "mean_error": bias.tolist(),
        })  # fmt: skip
        picks = " ".join(
            f"{centres[c]:.0f}:{bias[c] * 1e3:+.1f}" for c in range(0, bias.size, 8)
        )
        print(
            f"{sweeps:3d} sweeps  SAM {m['sam_deg']:.2f}°  PSNR {m['psnr_db']:.2f} dB  "
            f"mean error ×1e3 (nm:value) {picks}",
            flush=True,
        )
    if args.out:
        setup = {"size": [h, w], "threshold_noise": args.noise, "seed": args.seed,
                 "calibration": "true rig and threshold maps",
                 "lowpass_passes": cfg.lowpass_passes}  # fmt: skip
        Path(args.out).write_text(json.dumps({"setup": setup, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
