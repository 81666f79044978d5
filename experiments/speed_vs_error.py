"""Speed against error of every QP solver × iteration budget × float32/float64.

Setup: the paper's rig (threshold mismatch σ = 0.01, refractory 50 µs), one sweep of
the ColorChecker (default 48×72 px), reconstructed with the per-pixel thresholds (as
after calibration) so solver differences are not hidden under the threshold error. For
each solver configuration the full pipeline (events → cube, host grouping included,
compilation excluded) is timed: median of `--repeats` runs, in this one process.

Reported per configuration: pixels/s, SAM/PSNR against the truth, and the mean spectral
angle to the *converged answer* (the exact active-set solution in float64) — "equal
accuracy" means within 0.1° of it. Writes experiments/results/speed_vs_error.json and
.png (Pareto plot) and prints a markdown table.

Run: `.venv/bin/python experiments/speed_vs_error.py [--size 48x72] [--repeats 3]`
(about 10 min on 2 cores; the jaxopt solvers dominate).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.random as jr
import numpy as np

import evhsi_jax as ev

OUT = Path(__file__).parent / "results"

CONFIGS = [
    ("active-set", dict(iters=48, tol=1e-6)),
    ("unconstrained", {}),
    ("svd", {}),
    ("apg", dict(iters=100)),
    ("apg", dict(iters=300)),
    ("apg", dict(iters=1000)),
    ("apg", dict(iters=3000)),
    ("boxcdqp", dict(iters=50, tol=1e-9)),
    ("boxcdqp", dict(iters=200, tol=1e-9)),
    ("boxcdqp", dict(iters=1000, tol=1e-9)),
    ("boxcdqp", dict(iters=5000, tol=1e-9)),
    ("boxosqp", dict(iters=500, tol=1e-6)),
    ("boxosqp", dict(iters=4000, tol=1e-6)),
]


def run(dtype: str, size, repeats, configs):
    x64 = dtype == "float64"
    rows = []
    with jax.enable_x64(x64):
        rig = ev.Rig()
        scene = ev.load_scene("colorchecker", size)
        events, info = ev.simulate(
            scene, rig, sweeps=1, key=jr.key(0), return_info=True
        )
        truth = scene.truth_cube(rig.grid)
        kw = dict(
            threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
        )
        for name, opts in configs:
            spec = ev.SolverSpec(name, **opts)
            t0 = time.perf_counter()
            cube, rinfo = ev.reconstruct(
                events, rig, solver=spec, return_info=True, **kw
            )
            first = time.perf_counter() - t0
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                cube = ev.reconstruct(events, rig, solver=spec, **kw)
                times.append(time.perf_counter() - t0)
            m = ev.evaluate(cube, truth)
            rows.append(
                {
                    "solver": name,
                    **opts,
                    "dtype": dtype,
                    "px_per_s": scene.height * scene.width / float(np.median(times)),
                    "seconds_median": float(np.median(times)),
                    "first_call_s": first,
                    "kkt_max": float(np.nanmax(rinfo.kkt)),
                    "kkt_median": float(np.nanmedian(rinfo.kkt)),
                    **m,
                    "cube": cube,
                }
            )
            r = rows[-1]
            print(
                f"{dtype} {name:13s} {opts} {r['px_per_s']:9.0f} px/s  SAM "
                f"{m['sam_deg']:.3f}  PSNR {m['psnr_db']:.2f}  kkt {r['kkt_max']:.1e}",
                flush=True,
            )
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="48x72")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="fewer configurations")
    args = ap.parse_args()
    size = ev.parse_size(args.size)
    configs = CONFIGS if not args.quick else [CONFIGS[0], CONFIGS[3], CONFIGS[8]]
    rows = run("float32", size, args.repeats, configs) + run(
        "float64", size, args.repeats, configs
    )
    ref = next(
        r for r in rows if r["solver"] == "active-set" and r["dtype"] == "float64"
    )
    base = (
        next(
            r
            for r in rows
            if r["solver"] == "boxcdqp"
            and r["dtype"] == "float32"
            and r["iters"]
            == max(c[1].get("iters", 0) for c in configs if c[0] == "boxcdqp")
        )
        if any(c[0] == "boxcdqp" for c in configs)
        else None
    )
    for r in rows:
        r["sam_to_converged_deg"] = ev.sam_deg(r["cube"], ref["cube"])
        r["equal_accuracy"] = bool(r["sam_to_converged_deg"] <= 0.1)
    print(
        f"\n{len(rows)} runs, {size[0]}x{size[1]} px, machine: {os.cpu_count()} CPU "
        f"({platform.processor() or platform.machine()}), jax {jax.__version__}\n"
    )
    print(
        "| solver | budget | dtype | px/s | SAM° vs truth | PSNR dB | SAM° to converged |"
        " equal accuracy |"
    )
    print("|---|---|---|---:|---:|---:|---:|---|")
    for r in rows:
        budget = r.get("iters", "-")
        print(
            f"| {r['solver']} | {budget} | {r['dtype']} | {r['px_per_s']:,.0f} | "
            f"{r['sam_deg']:.3f} | {r['psnr_db']:.2f} | {r['sam_to_converged_deg']:.3f} | "
            f"{'yes' if r['equal_accuracy'] else 'no'} |"
        )
    fast = max(
        (r for r in rows if r["equal_accuracy"] and r["dtype"] == "float32"),
        key=lambda r: r["px_per_s"],
    )
    ref_cd = max(
        (
            r
            for r in rows
            if r["equal_accuracy"]
            and r["solver"] == "boxcdqp"
            and r["dtype"] == "float32"
        ),
        key=lambda r: r["px_per_s"],
        default=None,
    )
    summary = {
        "fastest_equal_accuracy_float32": {k: fast[k] for k in ("solver", "px_per_s")}
    }
    if ref_cd is not None:
        summary["speedup_vs_boxcdqp_equal_accuracy"] = (
            fast["px_per_s"] / ref_cd["px_per_s"]
        )
    elif base is not None:
        summary["boxcdqp_never_reached_equal_accuracy"] = True
        summary["speedup_vs_slowest_boxcdqp_budget"] = (
            fast["px_per_s"] / base["px_per_s"]
        )
    print("\n", json.dumps(summary))
    OUT.mkdir(exist_ok=True)
    for r in rows:
        r.pop("cube")
    (OUT / "speed_vs_error.json").write_text(
        json.dumps(
            {
                "size": list(size),
                "repeats": args.repeats,
                "cpus": os.cpu_count(),
                "rows": rows,
                "summary": summary,
            },
            indent=1,
        )
    )
    _plot(rows, OUT / "speed_vs_error.png")


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (solver, dtype), marker in zip(
        sorted({(r["solver"], r["dtype"]) for r in rows}), "os^vD<>ph*xP+"
    ):
        pts = sorted(
            (r["px_per_s"], max(r["sam_to_converged_deg"], 1e-4))
            for r in rows
            if r["solver"] == solver and r["dtype"] == dtype
        )
        xs, ys = zip(*pts)
        ax.loglog(
            xs,
            ys,
            marker + ("-" if dtype == "float32" else ":"),
            label=f"{solver} {dtype}",
        )
    ax.axhline(0.1, color="k", lw=0.5)
    ax.set_xlabel("pixels / s (full pipeline, 2 CPU cores)")
    ax.set_ylabel("SAM to converged answer (deg)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
