"""What knowing each sweep's mirror speed would gain: an oracle bound, not a method.

The `realistic` preset's mirror runs each sweep 0.2 % (σ) faster or slower
(`sweep_rate_jitter`; the simulator scales the sweep's β by a drawn factor, the
triggers stay on the nominal period), which neither `calibrate` nor `reconstruct`
estimates (README, Limitations). Late in a sweep that is a timing error of tens of µs.
This study reconstructs the same one-sweep captures twice — with the nominal rig and
with the sweep's true β (the simulator's drawn factor, `SimulationInfo.speed_factor`) —
both with the true per-pixel thresholds, so the difference is what an estimate of the
sweep's speed could at best recover. Captures: the ColorChecker at `--size`, the
preset (every effect on) and the mirror-speed jitter alone (0.2 %), for each of
`--seeds` (each seed draws another factor).

    python experiments/sweep_speed_oracle.py [--size 48x72] [--seeds 1,7]
"""

from __future__ import annotations

import argparse

import jax.random as jr
from _common import save

import evhsi_jax as ev

SENSORS = {
    "realistic preset": {"sensor": "realistic"},
    "mirror-speed jitter 0.2 % alone": {"sweep_rate_jitter": 0.002},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="48x72")
    ap.add_argument("--seeds", default="1,7")
    args = ap.parse_args()
    size = ev.forward.parse_size(args.size)
    scene = ev.load_scene("colorchecker", size)
    rows = []
    for name, keys in SENSORS.items():
        rig = ev.Rig.from_dict(keys)
        truth = scene.truth_cube(rig.grid)
        for seed in (int(s) for s in args.seeds.split(",")):
            events, info = ev.simulate(
                scene, rig, sweeps=1, key=jr.key(seed), return_info=True
            )
            maps = dict(
                threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
            )
            factor = float(info.speed_factor[0])
            known = rig.with_leaves(beta_nm_per_rad=rig.beta_nm_per_rad * factor)
            row = {"sensor": name, "seed": seed, "speed_factor": factor}
            for label, r in (("nominal", rig), ("true_speed", known)):
                m = ev.evaluate(ev.reconstruct(events, r, **maps), truth)
                row[label] = {"sam_deg": m["sam_deg"], "psnr_db": m["psnr_db"]}
            rows.append(row)
            print(
                f"{name:32s} seed {seed}: speed ×{factor:.5f}; nominal rig "
                f"{row['nominal']['sam_deg']:.2f}° / {row['nominal']['psnr_db']:.2f} dB,"
                f" the sweep's true speed {row['true_speed']['sam_deg']:.2f}° / "
                f"{row['true_speed']['psnr_db']:.2f} dB",
                flush=True,
            )
    save("sweep_speed_oracle", {"size": list(size), "rows": rows})


if __name__ == "__main__":
    main()
