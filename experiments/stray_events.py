"""Stray background events inside the lit interval: what they cost, what the search
for them (`ProblemConfig.stray_z`, `_pipeline.repair_strays`) gives back.

Setup: the training scene `tcs` (or `--scene`), the paper rig with background
activity of `--rates` Hz per pixel (otherwise ideal; `--sensor realistic`: the
`realistic` preset with that rate; `--keys '{"threshold_noise": 0.005}'`: more rig
keys), the true rig and per-pixel thresholds as the
calibration (no calibration error), 1 and 4 sweeps (`--sweeps`). The same capture
is also simulated without background activity (same key: the same signal events),
which labels each pixel: *inside* — a background event between its first and last
signal event; *untouched* — no background event at all. Each capture is
reconstructed with the search (`stray_z` 6, the default) and without (`stray_z`
0), fused backend. Printed per row: SAM / PSNR of the whole cube both ways, the
strays removed, the mean SAM of the *inside* pixels both ways, and how many
*untouched* pixels the search changed (it should change none).

    .venv/bin/python experiments/stray_events.py [--rates 1,3,20] [--sweeps 1,4]
        [--scene tcs] [--sensor ideal|realistic] [--keys JSON] [--size 32x48]
        [--out PATH]
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev
from evhsi_jax.reconstruction import ProblemConfig


def _pixel_events(events, w):
    x, y, t, p = (np.asarray(a) for a in (events.x, events.y, events.t_us, events.p))
    return list(zip((y.astype(np.int64) * w + x).tolist(), t.tolist(), p.tolist()))


def labels(clean, noisy, h, w):
    """Per pixel: a background event inside its lit span (first to last signal
    event), and any background event at all."""
    left = Counter(_pixel_events(clean, w))
    first, last = {}, {}
    for i, t, _ in sorted(left):
        first.setdefault(i, t)
        last[i] = t
    inside = np.zeros(h * w, bool)
    touched = np.zeros(h * w, bool)
    for e in _pixel_events(noisy, w):
        if left[e] > 0:
            left[e] -= 1
            continue
        i, t, _ = e
        touched[i] = True
        inside[i] |= i in first and first[i] <= t <= last[i]
    return inside, touched


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rates", default="1,3,20")
    ap.add_argument("--sweeps", default="1,4")
    ap.add_argument("--scene", default="tcs")
    ap.add_argument("--sensor", default="ideal", choices=["ideal", "realistic"])
    ap.add_argument("--keys", default="{}", help="more rig keys, a JSON object")
    ap.add_argument("--size", default="32x48")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    h, w = ev.forward.parse_size(args.size)
    scene = ev.load_scene(args.scene, (h, w))
    rows = []
    for sweeps in (int(v) for v in args.sweeps.split(",")):
        for rate in (float(v) for v in args.rates.split(",")):
            caps = {}
            for r in (0.0, rate):
                rig = ev.Rig(sensor=args.sensor).replace_host(
                    **json.loads(args.keys), noise_rate_hz=r
                )
                caps[r] = (rig, *ev.simulate(scene, rig, sweeps=sweeps,
                                             key=jr.key(args.seed), return_info=True))  # fmt: skip
            rig, events, info = caps[rate]
            inside, touched = labels(caps[0.0][1], events, h, w)
            truth = np.asarray(scene.truth_cube(rig.grid), np.float64)
            cal = ev.Calibration(rig, info.threshold_on, info.threshold_off)
            out = {}
            for z in (0.0, ProblemConfig().stray_z):
                cube, inf = ev.reconstruct(
                    events, cal, config=ProblemConfig(stray_z=z), backend="fused",
                    deblur=False, return_info=True,
                )  # fmt: skip
                out[z] = (cube, inf.stray_events, ev.evaluate(cube, truth))
            (c0, _, m0), (c1, n1, m1) = out[0.0], out[ProblemConfig().stray_z]
            s0 = ev.metrics.sam_map_deg(c0, truth).ravel()
            s1 = ev.metrics.sam_map_deg(c1, truth).ravel()
            changed = np.any(np.asarray(c0) != np.asarray(c1), axis=-1).ravel()
            row = {
                "sweeps": sweeps, "rate_hz": rate, "inside_pixels": int(inside.sum()),
                "off": {"sam_deg": m0["sam_deg"], "psnr_db": m0["psnr_db"]},
                "on": {"sam_deg": m1["sam_deg"], "psnr_db": m1["psnr_db"]},
                "strays_removed": n1,
                "inside_sam_off": float(s0[inside].mean()) if inside.any() else None,
                "inside_sam_on": float(s1[inside].mean()) if inside.any() else None,
                "untouched_changed": int((changed & ~touched).sum()),
            }  # fmt: skip
            rows.append(row)
            print(
                f"{sweeps} sweep(s), {rate:g} Hz: SAM/PSNR {m0['sam_deg']:.2f}°/"
                f"{m0['psnr_db']:.2f} dB -> {m1['sam_deg']:.2f}°/{m1['psnr_db']:.2f} dB; "
                f"{n1} strays removed; {row['inside_pixels']} pixels with one inside: "
                f"SAM {row['inside_sam_off'] or 0:.2f}° -> {row['inside_sam_on'] or 0:.2f}°;"
                f" untouched pixels changed: {row['untouched_changed']}",
                flush=True,
            )
    if args.out:
        setup = {"scene": args.scene, "size": [h, w], "sensor": args.sensor,
                 "keys": json.loads(args.keys),
                 "seed": args.seed, "calibration": "true rig and threshold maps",
                 "backend": "fused", "deblur": False}  # fmt: skip
        Path(args.out).write_text(json.dumps({"setup": setup, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
