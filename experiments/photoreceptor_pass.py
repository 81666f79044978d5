"""The photoreceptor pass: how fine its time grid, how many Gauss–Newton passes.
Speed against error.

With a photoreceptor in the calibration, the noise-aware reconstruction (README, Real
sensors) solves once with each event moved back by the filter's lag, then replaces
the event rows by the low-passed sensor model linearised at that answer and solves
again: Gauss–Newton passes, at most `ProblemConfig.lowpass_passes` (default 3;
`evhsi reconstruct --photoreceptor-passes`), a pixel taking another only while its
last one moved it by more than `lowpass_tol` (default 0.2), each on a uniform time
grid of
`rig.samples_per_sweep` points per sweep (1,200 on the paper rig: 27.8 µs steps,
longer than the 16 µs time constant at a white pixel's peak with a 10 kHz cut-off).
Both set the cost of the path real sensors take; this study measures what each buys.

Setup: the ColorChecker (or `--scene`) at `--size`, one sweep, the paper rig with each `--sensors`
entry (`lp`: a 10 kHz photoreceptor and nothing else; `realistic-3k`: the preset
with a 3 kHz photoreceptor; `realistic`: the preset, every
effect on — threshold noise 0.01, ON/OFF correlation 0.5, 5 µs jitter, 40 µs latency,
10 kHz photoreceptor, 1 Hz noise events, 0.1 % hot pixels at 1 kHz, 0.2 % rate
jitter, 0.5 px PSF, skewed band, 3 nm curvature). The simulator filters on its own
grid, the rig's `samples_per_sweep` times its oversampling (1 on this rig), so each
capture is made twice: on the rig's grid (the discretised filter the reconstruction
inverts) and on an 8× finer one (`--sim-fine`, nearer a continuous photoreceptor).
Each capture is reconstructed, on the fused backend with one thread (median of
`--repeats` warm calls), with the true rig and the true per-pixel thresholds, or with
`--calibrated` as a user would: `ev.calibrate` from a gray-chart capture of
`realism.CHART_SWEEPS` sweeps, started from what the user knows
(`realism.user_init`). Configurations: each of `--grids` (set through
`samples_per_sweep`, which in the reconstruction sets that grid only) with the
default passes, and each of `--passes` as a fixed number (tolerance 0) on the rig's
grid. Printed and written (`results/<--out>.json`):
seconds per call, SAM / PSNR against the truth, SAM to the default's cube.

    python experiments/photoreceptor_pass.py [--size 96x144]
        [--sensors lp,realistic,realistic-3k]
        [--grids 300,600,1200,2400,4800] [--passes 0,1,2,3] [--sim-fine 9600]
        [--calibrated] [--scene colorchecker] [--seed 1] [--repeats 3]
        [--out photoreceptor_pass]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax.random as jr
import numpy as np
from _common import matmul_gflops, save
from realism import CHART_SWEEPS, user_init

import evhsi_jax as ev
from evhsi_jax.reconstruction import ProblemConfig


def _rig(sensor: str) -> ev.Rig:
    if sensor == "lp":
        return ev.Rig(photoreceptor_hz=10_000.0)
    if sensor == "realistic-3k":  # a slower photoreceptor (lower bias current)
        return ev.Rig(sensor="realistic", photoreceptor_hz=3_000.0)
    return ev.Rig(sensor=sensor)


def _calibrated(rig: ev.Rig, size, seed: int) -> ev.Calibration:
    """What a user reconstructs with (as `realism.py`)."""
    chart = ev.load_scene("gray-chart", size)
    gray = ev.simulate(chart, rig, sweeps=CHART_SWEEPS, key=jr.key(seed))
    # `user_init(rig, cutoff="given")`: the cut-off given and kept, the setup of
    # this study's published figures (the calibration measures it by default).
    init = user_init(rig, cutoff="given")
    return ev.calibrate(gray, chart, init, fit_photoreceptor=False).calibration


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--sensors", default="lp,realistic,realistic-3k")
    ap.add_argument("--grids", default="300,600,1200,2400,4800")
    ap.add_argument("--passes", default="0,1,2,3")
    ap.add_argument("--sim-fine", type=int, default=9600)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--calibrated",
        action="store_true",
        help="reconstruct with a gray-chart calibration instead of the true rig",
    )
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--scene", default="colorchecker", help="e.g. tcs (the weights' training scene)"
    )
    ap.add_argument("--out", default="photoreceptor_pass")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    default = ProblemConfig()
    # (grid, passes, tol): the grids with the default passes, then each fixed
    # number of passes (tol 0: every pixel takes them all) on the rig's grid.
    configs = [(int(g), default.lowpass_passes, default.lowpass_tol)
               for g in args.grids.split(",")]  # fmt: skip
    configs += [(None, int(p), 0.0) for p in args.passes.split(",")]
    scene = ev.load_scene(args.scene, (h, w))
    rows = []
    for sensor in args.sensors.split(","):
        rig = _rig(sensor)
        truth = scene.truth_cube(rig.grid)
        cal = _calibrated(rig, (h, w), args.seed) if args.calibrated else None
        for sim_grid in (rig.samples_per_sweep, args.sim_fine):
            sim_rig = rig.replace_static(samples_per_sweep=sim_grid)
            events, info = ev.simulate(
                scene, sim_rig, sweeps=1, key=jr.key(args.seed), return_info=True
            )
            if cal is None:  # the true rig and the true per-pixel thresholds
                maps = dict(
                    threshold_on_map=info.threshold_on,
                    threshold_off_map=info.threshold_off,
                )
            else:  # the calibration's own maps
                maps = {}
            base = None
            first = len(rows)
            for g, passes, tol in configs:
                g = rig.samples_per_sweep if g is None else g
                if cal is None:
                    c = rig.replace_static(samples_per_sweep=g)
                else:
                    c = dataclasses.replace(
                        cal, rig=cal.rig.replace_static(samples_per_sweep=g)
                    )
                cfg = dataclasses.replace(default, lowpass_passes=passes, lowpass_tol=tol)

                def call(c=c, cfg=cfg):
                    return ev.reconstruct(
                        events, c, config=cfg, backend="fused", threads=1, **maps
                    )

                call()  # warm-up (numba's cache, the rig's tables)
                times = []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    cube = call()
                    times.append(time.perf_counter() - t0)
                m = ev.evaluate(cube, truth)
                is_default = (
                    g == rig.samples_per_sweep
                    and (passes, tol) == (default.lowpass_passes, default.lowpass_tol)
                )
                if is_default:
                    base = cube
                rows.append(
                    {
                        "sensor": sensor,
                        "calibration": "gray chart" if cal is not None else "true rig",
                        "sim_grid": sim_grid,
                        "grid": g,
                        "passes": passes,
                        "tol": tol,
                        "seconds": statistics.median(times),
                        "sam_deg": m["sam_deg"],
                        "psnr_db": m["psnr_db"],
                        "cube": cube,
                    }
                )
            for row in rows[first:]:
                cube = row.pop("cube")
                row["sam_to_default_deg"] = float(
                    np.nanmean(ev.metrics.sam_map_deg(cube, base))
                )
                print(
                    f"{sensor:10s} sim grid {sim_grid:5d}  grid {row['grid']:5d} "
                    f"passes {row['passes']} tol {row['tol']}: {row['seconds']:.3f} s, SAM "
                    f"{row['sam_deg']:.3f}° PSNR {row['psnr_db']:.2f} dB, to the "
                    f"default's cube {row['sam_to_default_deg']:.3f}°",
                    flush=True,
                )
    gflops = matmul_gflops()
    print(f"float32 matmul {gflops:.0f} GFLOP/s")
    save(
        args.out,
        {
            "size": [h, w],
            "scene": args.scene,
            "seed": args.seed,
            "repeats": args.repeats,
            "calibration": "gray chart" if args.calibrated else "true rig",
            "matmul_gflops": gflops,
            "rows": rows,
        },
    )


if __name__ == "__main__":
    main()
