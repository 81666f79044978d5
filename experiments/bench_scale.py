"""Benchmark: per-sweep reconstruction speed at 1280×720, and scaling over devices.

Setup: the paper rig, the ColorChecker at 720×1280, simulated once per run (cached as
an EVT 3.0 file under a temporary folder: ~50 MB per sweep, too big for results/),
then reconstructed sweep by sweep with `reconstruct_sweeps` (solver `auto`, known
per-pixel thresholds). The first sweep pays the compilations; the warm rate is the
median over the later sweeps. Scaling: a ColorChecker recording of `--scale-size`
(180×320) on 1, 2 and 4 devices of a `pixel_mesh` (sub-batch 1, what several CPU devices must
use, see `reconstruct`'s `mesh`), plus 1 device at the default sub-batch 128, each in a
fresh process with
`XLA_FLAGS=--xla_force_host_platform_device_count=N` (forced host devices share the
machine's cores, so on CPU this measures overhead, not speed-up). The simulator's
column chunks are timed on 1 and 4 devices too.

    python experiments/bench_scale.py            # 1280x720 + scaling: ~12 min on 2 cores
    python experiments/bench_scale.py --quick    # scaling only (180x320), ~5 min; keeps
                                                 # the 1280x720 entry of the last full run
    python experiments/bench_scale.py --full-only  # the 1280x720 run only; keeps the
                                                   # scaling entries of the last run

Writes results/bench_scale.json and .png.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).parent


def child(args) -> dict:
    """Runs in a fresh process with the device count already set."""
    import jax
    import jax.random as jr
    import numpy as np

    import evhsi_jax as ev

    h, w = (int(v) for v in args.size.split("x"))
    rig = ev.Rig()
    mesh = ev.sharding.pixel_mesh(args.devices) if args.devices > 1 else None
    scene = ev.load_scene("colorchecker", (h, w))
    key = jr.key(0)
    ev_path = Path(args.cache) / f"cc_{h}x{w}_{args.sweeps}.raw"
    thr_path = ev_path.with_suffix(".thr.npz")
    out = {"devices": args.devices, "size": [h, w], "backend": jax.default_backend()}
    if args.simulate or not ev_path.exists():
        t0 = time.perf_counter()
        events, info = ev.simulate(
            scene, rig, sweeps=args.sweeps, key=key, return_info=True, mesh=mesh
        )
        out["simulate_s"] = time.perf_counter() - t0
        out["events"] = len(events)
        if not ev_path.exists():
            ev.write_events(ev_path, events)
            np.savez(thr_path, on=info.threshold_on, off=info.threshold_off)
        del events
    if args.simulate_only:
        return out
    thr = np.load(thr_path)
    res_dir = Path(tempfile.mkdtemp(dir=args.cache))
    t0 = time.perf_counter()
    res = ev.reconstruct_sweeps(
        ev_path,
        rig,
        res_dir / "cubes",
        threshold_on_map=thr["on"],
        threshold_off_map=thr["off"],
        mesh=mesh,
        preview=False,
        sub_batch=args.sub_batch,
    )
    out["reconstruct_total_s"] = time.perf_counter() - t0
    secs = [e["seconds"] for e in res.index["sweeps"]]
    out["sweep_seconds"] = secs
    warm = float(np.median(secs[1:])) if len(secs) > 1 else secs[0]
    out["warm_s_per_sweep"] = warm
    out["sweeps_per_s"] = 1.0 / warm
    out["pixels_per_s"] = h * w / warm
    out["sub_batch_used"] = 1 if (mesh is not None) else args.sub_batch
    return out


def run_child(devices, size, sweeps, cache, *, simulate=False, sim_only=False, sub=128):
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    cmd = [
        sys.executable,
        __file__,
        "--child",
        "--devices",
        str(devices),
        "--size",
        size,
        "--sweeps",
        str(sweeps),
        "--cache",
        str(cache),
        "--sub-batch",
        str(sub),
    ]
    if simulate:
        cmd.append("--simulate")
    if sim_only:
        cmd.append("--simulate-only")
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)
    stdout, _ = proc.communicate()
    if proc.returncode:
        raise RuntimeError(f"child failed: {' '.join(cmd)}")
    rec = json.loads(stdout.strip().splitlines()[-1])
    rec["process_wall_s"] = time.perf_counter() - t0
    print(json.dumps(rec), flush=True)
    return rec


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--child", action="store_true")
    p.add_argument("--devices", type=int, default=1)
    p.add_argument("--size", default="720x1280")
    p.add_argument("--scale-size", default="180x320", help="image size of the scaling")
    p.add_argument("--sweeps", type=int, default=2, help="sweeps of the full run")
    p.add_argument("--scale-sweeps", type=int, default=3, help="sweeps per scaling run")
    p.add_argument("--cache", default=None)
    p.add_argument("--simulate", action="store_true")
    p.add_argument("--simulate-only", action="store_true")
    p.add_argument("--sub-batch", type=int, default=128)
    p.add_argument(
        "--quick",
        action="store_true",
        help="only the scaling runs; keep the full-size result already in the JSON",
    )
    p.add_argument(
        "--full-only",
        action="store_true",
        help="only the full-size run; keep the scaling results already in the JSON",
    )
    args = p.parse_args()
    if args.quick and args.full_only:
        p.error("--quick and --full-only exclude each other")
    if args.child:
        print(json.dumps(child(args)))
        return
    sys.path.insert(0, str(HERE))
    from _common import OUT, machine, matmul_gflops, pyplot

    cache = Path(args.cache or tempfile.mkdtemp(prefix="evhsi_bench_"))
    cache.mkdir(exist_ok=True)
    t_all = time.perf_counter()
    previous = OUT / "bench_scale.json"
    if args.quick:  # keep the full-size run of an earlier `python bench_scale.py`
        old = json.loads(previous.read_text()) if previous.is_file() else {}
        full = old.get("full")
        full_command = old.get("full_command", old.get("command"))
    else:
        full = run_child(1, args.size, args.sweeps, cache, simulate=True)
        full_command = "python experiments/bench_scale.py"
    # Several CPU devices must solve one pixel per lax.map step (sub_batch_for), which
    # on one device is slower than its default 128: measure one device both ways, so
    # the scaling compares like with like and the default stays visible.
    if args.full_only:  # keep the scaling runs of an earlier run
        old = json.loads(previous.read_text()) if previous.is_file() else {}
        scaling, sim_scaling = old.get("scaling", []), old.get("simulate_scaling", [])
        scaling_command = old.get("scaling_command", old.get("command"))
    else:
        scaling = []
        for d, sub in ((1, args.sub_batch), (1, 1), (2, 1), (4, 1)):
            rec = run_child(d, args.scale_size, args.scale_sweeps, cache, sub=sub)
            scaling.append(rec)
        sim_scaling = [
            run_child(d, args.scale_size, 1, cache, simulate=True, sim_only=True)
            for d in (1, 4)
        ]
        scaling_command = "python experiments/bench_scale.py" + (
            " --quick" if args.quick else ""
        )
    payload = {
        "command": "python experiments/bench_scale.py"
        + (" --quick" if args.quick else "")
        + (" --full-only" if args.full_only else ""),
        "scaling_command": scaling_command,
        "full_command": full_command,
        "machine": machine(),
        "matmul_gflops": matmul_gflops(),
        "reconstruct_backend": "auto (the fused CPU backend on a CPU)",
        "cpu_count": os.cpu_count(),
        "load_average_at_end": os.getloadavg(),
        "full": full,
        "scaling": scaling,
        "simulate_scaling": sim_scaling,
        "wall_s": time.perf_counter() - t_all,
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "bench_scale.json").write_text(json.dumps(payload, indent=1))
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    one = [r for r in scaling if r["sub_batch_used"] == 1]
    ax[0].plot(
        [r["devices"] for r in one],
        [r["pixels_per_s"] for r in one],
        "o-",
        label="sub-batch 1 (what several CPU devices run)",
    )
    for r in scaling:
        if r["sub_batch_used"] != 1:
            ax[0].plot(
                [r["devices"]],
                [r["pixels_per_s"]],
                "s",
                label=f"1 device, sub-batch {r['sub_batch_used']} (default)",
            )
    ax[0].set_xticks([1, 2, 4])
    ax[0].set_xlabel("CPU devices (forced; they share 2 cores)")
    ax[0].set_ylabel("pixels / s (warm)")
    ax[0].set_title(f"reconstruction, {args.scale_size}")
    ax[0].legend(fontsize=7)
    ax[1].bar(
        [str(r["devices"]) for r in sim_scaling],
        [r["simulate_s"] for r in sim_scaling],
    )
    ax[1].set_xlabel("CPU devices")
    ax[1].set_ylabel("s per sweep (incl. compile)")
    ax[1].set_title(f"simulation, {args.scale_size}")
    fig.tight_layout()
    fig.savefig(OUT / "bench_scale.png", dpi=110)
    print(f"wrote {OUT / 'bench_scale.json'} and .png")


if __name__ == "__main__":
    main()
