"""Time and memory of the joint calibration fit at a given sensor width.

Simulates a 2-sweep gray-chart capture of `--height` × `--width` pixels from
`true_rig.json` (with `config.json`'s column-offset wiggle and camera tilt), then times
`evhsi_jax.calibrate` from the paper rig (global fit + per-pixel threshold maps) and
reports wall time, Levenberg–Marquardt steps, the process's peak resident memory and the
parameter errors against the truth. Writes `calib/out/bench_calibration_<W>.json`.

Run: `.venv/bin/python calib/bench_calibration.py --width 1280` (~5 min and ~11 GB
peak on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import jax.random as jr
from run_calibration import rms, true_rig, true_values

import evhsi_jax as ev

HERE = Path(__file__).parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=48)
    ap.add_argument("--rows-per-patch", type=int, default=4)
    args = ap.parse_args()
    cfg = json.loads((HERE / "config.json").read_text())
    h, w = args.height, args.width
    truth = true_rig(cfg, w, HERE)
    chart = ev.load_scene("gray-chart", (h, w))
    events, sim = ev.simulate(chart, truth, sweeps=2, key=jr.key(3), return_info=True)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    res = ev.calibrate(events, chart, ev.Rig(), rows_per_label=args.rows_per_patch)
    wall = time.perf_counter() - t0
    rig = res.rig
    true_vals = true_values(truth, sim)
    out = {
        "command": f"python calib/bench_calibration.py --width {w} --height {h} "
        f"--rows-per-patch {args.rows_per_patch}",
        "size": [h, w],
        "events": len(events),
        "events_used": res.events_used,
        "seconds": wall,
        "steps": res.steps,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_fit_mb": rss0,
        "error_pct": {
            k: 100 * (float(getattr(rig, k)) / v - 1) for k, v in true_vals.items()
        },
        "tau_rms_error_us": rms(rig.column_offsets_us, truth.column_offsets(w)),
        "threshold_map_rms": rms(res.threshold_on_map, sim.threshold_on),
    }
    path = HERE / "out" / f"bench_calibration_{w}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
