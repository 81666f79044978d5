"""Video: a moving scene recorded for several seconds, reconstructed sweep by sweep.

Setup: the paper rig (30 sweeps/s), the `mixed` dynamic scene (the ColorChecker gliding
at 0.5 px/sweep and turning at 1°/sweep over a gray background, beside an iridescent disc
whose reflectance peak moves with a rocking viewing angle), 60×90 pixels. The simulator
runs once for the longest recording and writes it as an EVT 3.0 `.raw` (with encoder
triggers); the shorter recording is its first sweeps, cut by time. Each recording is then
reconstructed by the command-line tool, in a fresh process:

    evhsi reconstruct REC.raw --calib calib.json --out DIR --per-sweep --quiet

(known per-pixel thresholds through the calibration's `threshold_map`; solver `auto`),
and the process's peak resident memory is read as it exits (Linux `VmHWM`). For
contrast, another fresh process reads the whole file at once (`read_events`). Every
sweep's cube is scored against that sweep's truth: SAM (degrees) and PSNR (dB), on all
pixels and split by whether the pixel's material changed since the previous sweep (there
the carried reference is an approximation). Sweeps 1-5 are also reconstructed each on
its own with the baseline taken at the sweep start (no carried reference), as an
ablation. A short recording of each of the three
single-motion presets (`translate`, `rotate`, `iridescent`) is scored the same way.

    python experiments/video.py            # 60x90, 30 and 120 sweeps: ~10 min on 2 cores
    python experiments/video.py --quick    # 24x36, 6 and 12 sweeps: ~2 min (video_quick.*)

    python experiments/video.py --peak reconstruct REC.raw --calib C.json --out D \\
        --per-sweep --quiet           # peak memory of any one evhsi command

Writes results/video.json, results/video.png and results/video_preview.gif (the long
recording's `preview.gif`); with --keep DIR the recordings and datasets stay in DIR.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev

HERE = Path(__file__).parent
NAIVE_SWEEPS = (1, 2, 3, 4, 5)


# Peak memory is the child's own VmHWM (/proc/self/status), read as it exits: Linux's
# ru_maxrss of a child (os.wait4, getrusage) keeps the high-water mark of the process
# it was forked from, here the simulating parent, and so measures the parent.
PEAK = """
import atexit, os, sys
def _peak():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            open(os.environ["EVHSI_PEAK_FILE"], "w").write(line.split()[1])
atexit.register(_peak)
"""
CLI = PEAK + "from evhsi_jax.cli import main; sys.exit(main(sys.argv[1:]))"
READ_WHOLE = PEAK + "import evhsi_jax as ev; print(len(ev.read_events(sys.argv[1])))"


def measured(code: str, args: list[str], work: Path) -> dict:
    """Run Python `code` with `args` in a fresh process; wall time, peak RSS (MiB)."""
    peak_file = work / "peak_kib.txt"
    peak_file.unlink(missing_ok=True)
    env = {**os.environ, "EVHSI_PEAK_FILE": str(peak_file)}
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", code, *args], env=env, capture_output=True, text=True
    )
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise RuntimeError(f"{' '.join(args)} failed: {proc.stderr[-2000:]}")
    kib = int(peak_file.read_text())
    return {"wall_s": wall, "peak_rss_mib": kib / 1024, "stdout": proc.stdout}


def score(out_dir: Path, scenes, rig) -> list[dict]:
    """Per-sweep SAM/PSNR of a per-sweep dataset against the per-sweep truth."""
    changed = ev.forward.changed_pixels(scenes, rig.grid)
    rows = []
    for entry, data in ev.video.iter_sweep_cubes(out_dir):
        k = entry["sweep"]
        truth = scenes[k].truth_cube(rig.grid)
        sam = ev.metrics.sam_map_deg(data["cube"], truth)
        chg = changed[k]
        rows.append(
            {
                "sweep": k,
                "events": entry["events"],
                "low_events": entry["low_events"],
                "sam_deg": float(sam.mean()),
                "psnr_db": ev.metrics.psnr_db(data["cube"], truth),
                "sam_static_deg": float(sam[~chg].mean()) if (~chg).any() else None,
                "sam_changed_deg": float(sam[chg].mean()) if chg.any() else None,
                "changed_frac": float(chg.mean()),
            }
        )
    return rows


def summary(rows: list[dict]) -> dict:
    def stats(key):
        v = np.array([r[key] for r in rows if r[key] is not None], np.float64)
        if not v.size:
            return None
        return {
            "mean": float(v.mean()),
            "median": float(np.median(v)),
            "min": float(v.min()),
            "max": float(v.max()),
        }

    keys = ("sam_deg", "psnr_db", "sam_static_deg", "sam_changed_deg")
    return {
        "sweeps": len(rows),
        "flagged_low_events": [r["sweep"] for r in rows if r["low_events"]],
        **{k: stats(k) for k in keys},
    }


def presets(size, sweeps, work: Path, rig) -> dict:
    """Short recordings of the single-motion presets, reconstructed in this process."""
    out = {}
    for name in ("translate", "rotate", "iridescent"):
        scenes = ev.forward.dynamic_scene(name, size, sweeps=sweeps)
        events, info = ev.simulate(
            scenes, rig, sweeps=sweeps, key=jr.key(1), return_info=True
        )
        res = ev.reconstruct_sweeps(
            events,
            rig,
            work / f"preset_{name}",
            threshold_on_map=info.threshold_on,
            threshold_off_map=info.threshold_off,
            preview=False,
        )
        out[name] = summary(score(res.out_dir, scenes, rig))
        print(name, json.dumps(out[name]["sam_deg"]), flush=True)
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="60x90", help="HxW (default 60x90)")
    p.add_argument("--sweeps", default="30,120", help="the two lengths, in sweeps")
    p.add_argument("--preset-sweeps", type=int, default=12)
    p.add_argument("--quick", action="store_true", help="24x36, 6 and 12 sweeps")
    p.add_argument("--keep", metavar="DIR", help="keep recordings and datasets here")
    p.add_argument(
        "--peak",
        nargs=argparse.REMAINDER,
        metavar="EVHSI_ARGS",
        help="only run `evhsi EVHSI_ARGS` in a fresh process and print its peak RSS",
    )
    args = p.parse_args()
    if args.peak:
        run = measured(CLI, args.peak, Path(tempfile.mkdtemp(prefix="evhsi_peak_")))
        print(f"peak RSS {run['peak_rss_mib']:.0f} MiB, wall {run['wall_s']:.1f} s")
        return
    if args.quick:
        args.size, args.sweeps, args.preset_sweeps = "24x36", "6,12", 4
    name = "video_quick" if args.quick else "video"  # a smoke run keeps the real one
    size = ev.forward.parse_size(args.size)
    lengths = sorted(int(v) for v in args.sweeps.split(","))
    if len(lengths) != 2 or lengths[0] < 2:
        raise SystemExit("--sweeps: two lengths of at least 2 sweeps, e.g. 30,120")
    sys.path.insert(0, str(HERE))
    from _common import OUT, pyplot, save

    work = Path(args.keep or tempfile.mkdtemp(prefix="evhsi_video_"))
    work.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    rig = ev.Rig()
    n_max = lengths[-1]

    # 1. Simulate the longest recording once; the short one is its first sweeps.
    scenes = ev.forward.dynamic_scene("mixed", size, sweeps=n_max)
    t0 = time.perf_counter()
    events, info = ev.simulate(
        scenes, rig, sweeps=n_max, key=jr.key(0), return_info=True
    )
    sim_s = time.perf_counter() - t0
    np.savez(
        work / "thresholds.npz",
        threshold_on=info.threshold_on,
        threshold_off=info.threshold_off,
    )
    (work / "calib.json").write_text(json.dumps({"threshold_map": "thresholds.npz"}))
    recs = {}
    for n in lengths:
        path = work / f"mixed_{n}.raw"
        part = events.time_window(0, int(round(n * float(rig.period_us))))
        ev.write_events(path, part)
        recs[n] = {
            "file": path.name,
            "sweeps": n,
            "seconds_of_recording": n * float(rig.period_us) * 1e-6,
            "events": len(part),
            "bytes": path.stat().st_size,
        }
    # The per-sweep reference, ablated: each sweep alone with the baseline taken at
    # its start (what cutting the file into sweeps and calling reconstruct gives).
    sw = ev.io.split_sweeps(events)
    naive = {}
    for k in NAIVE_SWEEPS:
        cube = ev.reconstruct(
            sw[k],
            rig,
            t_start_us=int(sw.start_us[k]),
            threshold_on_map=info.threshold_on,
            threshold_off_map=info.threshold_off,
        )
        naive[k] = ev.metrics.sam_deg(cube, scenes[k].truth_cube(rig.grid))
    del events, part, sw
    print(f"simulated {n_max} sweeps of {size} in {sim_s:.1f} s", flush=True)

    # 2. Reconstruct each length in a fresh process; peak memory of each.
    for n in lengths:
        rec = recs[n]
        out_dir = work / f"cubes_{n}"
        args_ = ["reconstruct", str(work / rec["file"]), "--calib"]
        args_ += [str(work / "calib.json"), "--out", str(out_dir), "--per-sweep"]
        run = measured(CLI, [*args_, "--quiet", "--restart"], work)
        whole = measured(READ_WHOLE, [str(work / rec["file"])], work)
        index = ev.video.load_sweep_index(out_dir)
        secs = [e["seconds"] for e in index["sweeps"]]
        rows = score(out_dir, scenes, rig)
        rec.update(
            command=" ".join(["evhsi", *args_]),
            reconstruct_wall_s=run["wall_s"],
            peak_rss_mib=run["peak_rss_mib"],
            read_whole_peak_rss_mib=whole["peak_rss_mib"],
            cli_summary=run["stdout"].strip(),
            warm_s_per_sweep=float(np.median(secs[1:])),
            first_sweep_s=secs[0],
            preview=index["preview"],
            summary=summary(rows),
            per_sweep=rows,
        )
        print(
            f"{n} sweeps: peak RSS {run['peak_rss_mib']:.0f} MiB (read whole: "
            f"{whole['peak_rss_mib']:.0f} MiB), SAM "
            f"{rec['summary']['sam_deg']['mean']:.2f} deg",
            flush=True,
        )
        if n == n_max:
            OUT.mkdir(exist_ok=True)
            shutil.copy(out_dir / index["preview"], OUT / f"{name}_preview.gif")

    per = {r["sweep"]: r["sam_deg"] for r in recs[n_max]["per_sweep"]}
    reference = [
        {"sweep": k, "sam_carried_deg": per[k], "sam_baseline_at_start_deg": naive[k]}
        for k in NAIVE_SWEEPS
    ]
    print("reference ablation", json.dumps(reference), flush=True)

    # 3. The single-motion presets, short.
    pre = presets(size, args.preset_sweeps, work, rig)

    payload = {
        "command": "python experiments/video.py" + (" --quick" if args.quick else ""),
        "setup": {
            "scene": "mixed",
            "size": list(size),
            "lengths_sweeps": lengths,
            "sweep_rate_hz": float(rig.sweep_rate_hz),
            "solver": "auto",
            "thresholds": "known per-pixel maps (calibration threshold_map)",
            "preset_sweeps": args.preset_sweeps,
        },
        "simulate_s": sim_s,
        "recordings": [recs[n] for n in lengths],
        "reference_ablation": reference,
        "presets": pre,
        "work_dir": str(work) if args.keep else None,
        "wall_s": time.perf_counter() - t_all,
    }
    fig = figure(pyplot(), recs, lengths, scenes, rig, work)
    save(name, payload, fig)
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)


def figure(plt, recs, lengths, scenes, rig, work):
    long = recs[lengths[-1]]
    rows = long["per_sweep"]
    fig = plt.figure(figsize=(11, 6.4))
    gs = fig.add_gridspec(2, 4)
    ax = fig.add_subplot(gs[0, :2])
    k = [r["sweep"] for r in rows]
    ax.plot(k, [r["sam_deg"] for r in rows], label="all pixels")
    ax.plot(
        k,
        [r["sam_static_deg"] for r in rows],
        label="unchanged since last sweep",
        lw=0.8,
    )
    ax.set_xlabel("sweep")
    ax.set_ylabel("SAM (deg)")
    ax.set_title(f"per-sweep SAM, {lengths[-1]} sweeps")
    ax.legend(fontsize=8)
    ax2 = fig.add_subplot(gs[0, 2:])
    names = [f"{n} sweeps" for n in lengths]
    x = np.arange(len(lengths))
    ax2.bar(x - 0.2, [recs[n]["peak_rss_mib"] for n in lengths], 0.4, label="stream")
    ax2.bar(
        x + 0.2,
        [recs[n]["read_whole_peak_rss_mib"] for n in lengths],
        0.4,
        label="read whole file",
    )
    ax2.set_xticks(x, names)
    ax2.set_ylabel("peak RSS (MiB)")
    ax2.set_title("peak memory of a fresh process")
    ax2.legend(fontsize=8)
    out_dir = work / f"cubes_{lengths[-1]}"
    picks = np.linspace(0, len(rows) - 1, 4).astype(int)
    entries = ev.video.load_sweep_index(out_dir)["sweeps"]
    for j, s in enumerate(picks):
        a = fig.add_subplot(gs[1, j])
        cube = ev.load_cube(out_dir / entries[s]["file"])["cube"]
        truth = scenes[s].truth_cube(rig.grid)
        srgb = np.concatenate(
            [
                ev.cube_to_srgb(truth, rig.wavelengths_nm),
                ev.cube_to_srgb(cube, rig.wavelengths_nm),
            ]
        )
        a.imshow(np.clip(srgb, 0, 1))
        a.set_title(f"sweep {s}: truth / recon", fontsize=8)
        a.axis("off")
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
