"""Live reconstruction: latency from a sweep's last event to its cube on disk, and the
largest region that keeps up with 10 and 30 sweeps/s on this machine.

A simulated ColorChecker recording (paper rig, ideal sensor) is written to a `.raw` file
by a writer process at its real rate (`evhsi_jax._io.replay_raw`) while
`reconstruct_sweeps(..., follow=True)` reconstructs it. Per sweep:

- *latency* = wall time when the sweep's cube file was written − wall time when the
  writer appended the block holding the sweep's last event. A sweep is complete only
  when the next one's events start (or the recording ends), so the latency includes
  the dark gap between the two sweeps' lit intervals (~8 ms at 30 sweeps/s), then
  cutting, the solve and the atomic write;
- *keeps up* = the run finishes within one sweep period of the writer.

Then, for region sizes from 16×16 up, the warm per-sweep solve rate (sweeps/s) of the
streaming path on the finished file (medians of 3, one process) and the largest square
region whose rate is ≥ 10 and ≥ 30 sweeps/s. The same run's float32 matmul GFLOP/s is
printed beside (machines differ).

    .venv/bin/python experiments/live_latency.py [--size 64x96] [--sweeps 300]
        [--speed 1] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax.random as jr
import numpy as np
from _common import matmul_gflops

import evhsi_jax as ev


def live_run(raw: Path, cal, out: Path, roi=None, speed: float = 1.0) -> dict:
    marks_file = out.parent / "marks.json"
    code = (
        "import json, sys; from evhsi_jax._io import replay_raw; "
        f"m = replay_raw(sys.argv[1], sys.argv[2], speed={speed}); "
        "json.dump(m, open(sys.argv[3], 'w'))"
    )
    live = out.parent / "live.raw"
    writer = subprocess.Popen([sys.executable, "-c", code, str(raw), str(live),
                               str(marks_file)])  # fmt: skip
    while not live.exists() or live.stat().st_size == 0:
        time.sleep(0.005)
    done = {}
    res = ev.reconstruct_sweeps(
        live, cal, out, follow=True, idle_timeout_s=1.0, preview=False, roi=roi,
        on_sweep=lambda e: done.__setitem__(e["sweep"], (time.time(), e["stop_us"])),
    )  # fmt: skip
    writer.wait()
    marks = json.loads(marks_file.read_text())  # (wall, last event µs) per block
    m_wall = np.array([m[0] for m in marks])
    m_t = np.array([m[1] for m in marks])
    lat = []
    for k, (t_cube, stop_us) in sorted(done.items()):
        # the first block whose events reach the sweep's end holds its last event
        i = int(np.searchsorted(m_t, stop_us - 1, side="left"))
        i = min(i, len(m_wall) - 1)
        lat.append(t_cube - m_wall[i])
    lat = np.array(lat[1:-1])  # not the first (compilation) nor the last (idle end)
    # every sweep against the same run on the finished file
    ev.reconstruct_sweeps(raw, cal, out.parent / "offline", roi=roi, preview=False)
    pairs = zip(ev.video.iter_sweep_cubes(out), ev.video.iter_sweep_cubes(out.parent / "offline"))
    equal = [bool(np.array_equal(a["cube"], b["cube"])) for (_, a), (_, b) in pairs]
    return {
        "sweeps_equal_to_offline": f"{sum(equal)} of {len(equal)}",
        "sweeps": res.reconstructed,
        "latency_ms_median": float(np.median(lat) * 1e3),
        "latency_ms_p90": float(np.percentile(lat, 90) * 1e3),
        "latency_ms_max": float(lat.max() * 1e3),
        "finished_after_writer_s": float(max(t for t, _ in done.values()) - m_wall[-1]),
    }


def roi_rates(raw: Path, cal, work: Path, sizes, h, w) -> dict:
    rates = {}
    for s in sizes:
        if s > min(h, w):
            break
        roi = (0, 0, s, s)
        times = []
        for rep in range(4):  # the first run compiles
            out = work / f"roi{s}_{rep}"
            t = time.perf_counter()
            r = ev.reconstruct_sweeps(raw, cal, out, roi=roi, preview=False,
                                      max_sweeps=10)  # fmt: skip
            times.append(r.reconstructed / r.solve_seconds)
            del t
        rates[s] = float(np.median(times[1:]))
        print(f"  region {s}x{s}: {rates[s]:.1f} sweeps/s (solve only)", flush=True)
    return rates


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", default="128x160")
    p.add_argument("--sweeps", type=int, default=45)
    p.add_argument("--json", default="experiments/results/live_latency.json")
    p.add_argument(
        "--live-side", type=int, default=None, help="square region of the live run"
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="replay speed of the 30 sweeps/s recording (1/3: 10 sweeps/s)",
    )
    a = p.parse_args()
    h, w = (int(v) for v in a.size.split("x"))
    ev.enable_compilation_cache()
    gf = matmul_gflops()
    print(f"float32 matmul: {gf:.1f} GFLOP/s", flush=True)
    rig = ev.Rig()
    events = ev.simulate(ev.load_scene("colorchecker", (h, w)), rig, sweeps=a.sweeps,
                         key=jr.key(1))  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        raw = tmp / "rec.raw"
        ev.write_events(raw, events)
        cal = ev.Calibration(rig)
        rates = roi_rates(raw, cal, tmp, (16, 24, 32, 48, 64, 96, 128), h, w)
        best = {
            r: max([s for s, v in rates.items() if v >= r], default=None)
            for r in (10, 30)
        }
        (tmp / "live").mkdir()
        rate = 30 * a.speed
        side = a.live_side or (best[10] if rate <= 10 else best[30]) or 16
        live = live_run(raw, cal, tmp / "live" / "out", roi=(0, 0, side, side),
                        speed=a.speed)  # fmt: skip
        live["roi"] = [0, 0, side, side]
        live["sweeps_per_s"] = rate
        print(f"live, region {side}x{side}, {rate:.0f} sweeps/s: {live}", flush=True)
    out = {
        "matmul_gflops": gf,
        "size": [h, w],
        "sweeps": a.sweeps,
        "live": live,
        "roi_sweeps_per_s": rates,
        "largest_square_roi": best,
        "px_per_s_at_largest": {
            r: (rates[s] * s * s if s else None) for r, s in best.items()
        },
    }
    print(json.dumps(out, indent=1))
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
