"""Events per sweep and the maximum sweep rate versus constant light and threshold
(paper Fig. 12, supplement 7.2).

Setup. The paper's simulated rig (threshold spread σ = 0.01, refractory 50 µs, 30
sweeps/s) watching the ColorChecker, simulated at 24×36 pixels for one sweep, while the
constant light c (`baseline_rel`, a fraction of a white pixel's peak) and the contrast
threshold (`threshold_on` = `threshold_off`) vary.

Scaling to the IMX636 (1280×720). A pixel's events depend only on its own spectrum and
on the band's passage; the column offset only shifts them in time (the default stagger
spans 0.15 of the sweep at any sensor width). With the chart filling the field of view,
events per sweep on the full sensor = (mean events per simulated pixel) × 921 600. The
maximum sweep rate is then min(80 Mev/s ÷ events per sweep, 30 sweeps/s mechanical). The
80 Mev/s is treated as a limit on the average rate; the peak rate during a sweep, also
reported (1 ms bins at 30 sweeps/s, scaled the same way), is higher because the events
bunch where the band crosses the chart. Events per sweep depend weakly on the sweep rate
(the 50 µs refractory period drops events on the steepest flanks at high rates; checked
at 10/20/30 sweeps/s for the default settings), so the sensor-limited rate f0 from the
count at 30 sweeps/s is refined once by recounting at f0.

Run: `.venv/bin/python experiments/event_rate.py` (`--quick` for a smoke test).
Writes experiments/results/event_rate.json and event_rate.png.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax.random as jr
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline_common import RESULTS, machine, table, write_json  # noqa: E402

import evhsi_jax as ev  # noqa: E402

SENSOR = (720, 1280)
SENSOR_LIMIT_EV_S = 80e6
MECH_LIMIT_SWEEPS_S = 30.0
BASELINES = (0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.5)
THRESHOLDS = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4)
SIZE = (24, 36)


def count(scene, rig, key):
    """Mean events per pixel in one sweep, and the peak 1-ms rate per pixel (ev/s)."""
    events = ev.simulate(scene, rig, key=key)
    n_px = scene.height * scene.width
    period_us = float(rig.period_us)
    hist, _ = np.histogram(events.t_us, bins=np.arange(0.0, period_us + 1000.0, 1000.0))
    return len(events) / n_px, hist.max() / n_px / 1e-3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 × 2 settings at 8×12")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    size, baselines, thresholds = SIZE, BASELINES, THRESHOLDS
    if args.quick:
        size, baselines, thresholds = (8, 12), (0.01, 0.03, 0.1), (0.15, 0.3)
    scene = ev.load_scene("colorchecker", size)
    key = jr.key(args.seed)
    pixels = SENSOR[0] * SENSOR[1]
    rows = []
    for c in baselines:
        for thr in thresholds:
            rig = ev.Rig(baseline_rel=c, threshold_on=thr, threshold_off=thr)
            per_px, peak_px = count(scene, rig, key)
            per_sweep = per_px * pixels
            f0 = SENSOR_LIMIT_EV_S / per_sweep
            # One fixed-point step: at the slower rate f0 the refractory period drops
            # fewer events, so recount there (f1 ≤ f0).
            f1 = f0
            if f0 < MECH_LIMIT_SWEEPS_S:
                slow = ev.Rig(
                    baseline_rel=c,
                    threshold_on=thr,
                    threshold_off=thr,
                    sweep_rate_hz=round(f0, 2),
                )
                f1 = SENSOR_LIMIT_EV_S / (count(scene, slow, key)[0] * pixels)
            rows.append(
                {
                    "baseline_rel": c,
                    "threshold": thr,
                    "events_per_pixel": round(per_px, 2),
                    "Mev_per_sweep": round(per_sweep / 1e6, 3),
                    "sensor_limit_sweeps_s": round(f1, 2),
                    "max_sweeps_s": round(min(f1, MECH_LIMIT_SWEEPS_S), 2),
                    "mean_Mev_s_at_30": round(per_sweep * MECH_LIMIT_SWEEPS_S / 1e6, 1),
                    "peak_Mev_s_at_30": round(peak_px * pixels / 1e6, 1),
                }
            )
    cols = list(rows[0])
    print(
        table(
            rows,
            cols,
            f"ColorChecker, scaled from {size[0]}x{size[1]} to "
            "1280x720; limits 80 Mev/s and 30 sweeps/s",
        )
    )

    check = []
    for rate in (10.0, 20.0, 30.0):
        rig = ev.Rig(sweep_rate_hz=rate)
        per_px, _ = count(scene, rig, key)
        check.append({"sweep_rate_hz": rate, "events_per_pixel": round(per_px, 2)})
    print(
        table(
            check,
            ["sweep_rate_hz", "events_per_pixel"],
            "Check: events per sweep vs sweep rate (default c, threshold)",
        )
    )

    grid = {(r["baseline_rel"], r["threshold"]): r for r in rows}
    _figure(
        args.out / ("event_rate_quick.png" if args.quick else "event_rate.png"),
        grid,
        baselines,
        thresholds,
    )
    wall = round(time.perf_counter() - t0, 1)
    write_json(
        args.out / ("event_rate_quick.json" if args.quick else "event_rate.json"),
        {
            "setup": {
                "scene": "colorchecker",
                "simulated_size": list(size),
                "sensor": list(SENSOR),
                "sensor_limit_ev_s": SENSOR_LIMIT_EV_S,
                "mechanical_limit_sweeps_s": MECH_LIMIT_SWEEPS_S,
                "threshold_sigma": 0.01,
                "scaling": "events per sweep = mean events per simulated pixel × 1280·720",
                "seed": args.seed,
            },
            "rows": rows,
            "sweep_rate_check": check,
            "machine": machine(),
            "wall_s": wall,
        },
    )
    print(f"wall time {wall} s")
    return rows


def _figure(path, grid, baselines, thresholds):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for thr in thresholds:
        ev_s = [grid[(c, thr)]["Mev_per_sweep"] for c in baselines]
        fps = [grid[(c, thr)]["max_sweeps_s"] for c in baselines]
        axes[0].plot(baselines, ev_s, "o-", label=f"C = {thr}")
        axes[1].plot(baselines, fps, "o-", label=f"C = {thr}")
    axes[0].set_ylabel("Mev per sweep (1280×720)")
    axes[1].set_ylabel("max sweeps/s (80 Mev/s, 30/s mechanical)")
    axes[1].axhline(MECH_LIMIT_SWEEPS_S, color="k", ls=":", lw=0.8)
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("constant light c (fraction of white peak)")
        ax.legend(fontsize=7)
    axes[0].set_yscale("log")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
