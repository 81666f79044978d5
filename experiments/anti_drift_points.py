"""How many anti-drift points per sweep (`ProblemConfig.int_points`) the accuracy needs.

The anti-drift rows are about half of each pixel's rows, so their number sets much of
the reconstruction's cost. The default is chosen on the *training* scenes only (those
of `tune_weights.py`: `tcs`, 44 measured test-colour samples, and `sharp`, synthetic
steps and narrow peaks), never on the evaluation scenes; the ColorChecker is printed
beside them as a held-out check.

Setup: paper rig with the `--sensors` presets (`ideal`; `realistic`: threshold noise,
jitter, 10 kHz photoreceptor, noise events, hot pixels, ON/OFF correlation, latency,
PSF, skewed band, curvature, rate jitter — its noise model used by the
reconstruction), one sweep, seed 0; reconstructed with the true rig and the sensor's
per-pixel thresholds (as after calibration), default solver and backend, every
`int_points` of `--points`. SAM / PSNR against the truth.

`--speed`: also the fused kernel's time per pixel for each `int_points` (ColorChecker
96×144 of each preset, `_kernel_setup.fused_inputs`, every usable core; one warm-up
call, then `--repeats` rounds, each running every value once, so that the per-round
ratios to the first value are the least exposed to the machine's drift), with the
same run's float32 matmul GFLOP/s.

    python experiments/anti_drift_points.py [--points 32,24,20,16] \
        [--sensors ideal,realistic] [--speed] [--repeats 5]
        [--out experiments/results/anti_drift_points.json]

About 2 minutes on 2 cores (with `--speed`, 4).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax.random as jr
import numpy as np
from _common import matmul_gflops, timed_reconstruct, write_json
from tune_weights import sharp_scene

import evhsi_jax as ev

SCENES = {  # name: (scene factory, training scene?)
    "tcs": (lambda: ev.load_scene("tcs", (12, 44)), True),
    "sharp": (sharp_scene, True),
    "colorchecker": (lambda: ev.load_scene("colorchecker", (48, 72)), False),
}


def kernel_speed(sensor: str, points: list[int], repeats: int) -> dict:
    """µs per pixel of the fused kernel for each `int_points` (see --speed)."""
    from _kernel_setup import fused_inputs

    from evhsi_jax._reconstruct import _fused
    from evhsi_jax._reconstruct import _pipeline as pipe

    setup = fused_inputs(sensor, "96x144")
    rig = ev.Rig(sensor=sensor)
    w = setup.size[1]
    probs = {
        p: _fused.FusedProblem(
            rig, pipe.channel_table(rig),
            dataclasses.replace(ev.reconstruction.ProblemConfig(), int_points=p),
            pipe.solver_spec("auto"), w, np.asarray(rig.column_offsets(w), np.float64),
            1, pipe.noise_model(rig),
        )  # fmt: skip
        for p in points
    }
    times = {p: [] for p in points}
    for r in range(repeats + 1):  # round 0: warm-up (compiles)
        for p, prob in probs.items():
            t = time.perf_counter()
            _fused.solve_fused(prob, setup.sel, *setup.args)
            if r:
                times[p].append(time.perf_counter() - t)
    n = setup.sel.size
    ref = points[0]
    return {
        str(p): {
            "us_per_px_median": 1e6 * statistics.median(times[p]) / n,
            f"median_round_ratio_{ref}_over_this": statistics.median(
                a / b for a, b in zip(times[ref], times[p])
            ),
        }
        for p in points
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", default="32,24,20,16")
    ap.add_argument("--sensors", default="ideal,realistic")
    ap.add_argument("--speed", action="store_true")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    points = [int(v) for v in args.points.split(",")]
    rows, speed = [], {}
    for sensor in args.sensors.split(","):
        rig = ev.Rig(sensor=sensor)
        caps = {}
        for name, (make, _) in SCENES.items():
            scene = make()
            events, info = ev.simulate(
                scene, rig, sweeps=1, key=jr.key(0), return_info=True
            )
            caps[name] = (events, info, scene.truth_cube(rig.grid))
        for p in points:
            cfg = dataclasses.replace(ev.reconstruction.ProblemConfig(), int_points=p)
            line = []
            for name, (events, info, truth) in caps.items():
                cube, dt = timed_reconstruct(events, rig, info, config=cfg)
                m = ev.evaluate(cube, truth)
                rows.append({
                    "sensor": sensor, "int_points": p, "scene": name,
                    "training": SCENES[name][1], "sam_deg": m["sam_deg"],
                    "psnr_db": m["psnr_db"], "seconds": dt,
                })  # fmt: skip
                line.append(f"{name} {m['sam_deg']:.3f}° / {m['psnr_db']:.2f} dB")
            print(f"{sensor:9s} int_points {p:3d}: " + " | ".join(line), flush=True)
        if args.speed:
            speed[sensor] = kernel_speed(sensor, points, args.repeats)
            for p, v in speed[sensor].items():
                ratio = list(v.values())[1]
                print(f"{sensor:9s} int_points {p:>3s}: fused kernel "
                      f"{v['us_per_px_median']:.2f} µs/px (all cores), "
                      f"{points[0]} / this {ratio:.2f}x", flush=True)  # fmt: skip
    gflops = matmul_gflops() if args.speed else None
    if gflops:
        print(f"float32 matmul {gflops:.1f} GFLOP/s")
    if args.out:
        write_json(args.out, {
            "setup": "paper rig presets, 1 sweep, seed 0, true rig and per-pixel "
                     "thresholds; training scenes tcs 12x44, sharp 12x48; "
                     "ColorChecker 48x72 held out",
            "rows": rows, "kernel_speed": speed, "matmul_gflops": gflops,
        })  # fmt: skip


if __name__ == "__main__":
    main()
