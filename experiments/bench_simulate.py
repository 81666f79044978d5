"""Simulator throughput: one sweep of a full 1280×720 sensor with the paper rig.

Setup: the default `Rig()` (72 channels, 17.5 nm FWHM, 1200 samples per sweep at
30 sweeps/s, C ~ N(0.15, 0.01), 50 µs refractory, 3 % constant light) and two scenes of
the requested size (default 720×1280):

- `colorchecker`: the 24 ColorChecker spectra in a 4 × 6 layout — the simulator's
  *palette* path (one intensity trace per spectrum and column, gathered per pixel);
- `random`: a different smooth random spectrum at every pixel (three Gaussian bumps on
  a 10 nm grid, seeded) — the *per-pixel* path (one trace per pixel).

Each scene runs in a fresh worker process (so compile time and peak memory are its own):
one cold run (compilation included) and `--repeats` warm runs; we report the cold time,
the median (and min) warm wall time, compile ≈ cold − median warm, events/s, events per
pixel per sweep and the worker's peak resident set (`getrusage` ru_maxrss). Scene
construction is excluded from the timings. The issue's target: one full sweep in
under 10 s on 2 CPU cores (issue "Speed"; it was 60 s before). With `--profile` the
worker also times the pieces of one sweep (log-intensity stage, event scan,
device→host copy, event extraction, final sort; the two stages compiled separately,
as the palette path runs them). On a CPU with numba the scan is the compiled state
machine (`evhsi_jax/_simulate/_scan_jit.py`), which emits the crossings itself (no
copy, no extraction; `scan_kind` in the profile); elsewhere, or with
`EVHSI_NO_NUMBA=1`, the XLA scan. The record has the same run's float32 matmul
GFLOP/s.

usage: python experiments/bench_simulate.py [--size 720x1280] [--repeats 3]
       [--scenes colorchecker,random] [--chunk-columns 16] [--profile]
writes experiments/results/bench_simulate[_HxW].json and .png, prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
SCENES = ("colorchecker", "random")
TARGET_S = 10.0


def random_scene(height: int, width: int, seed: int = 0):
    """A smooth random reflectance spectrum per pixel: 0.1 + three Gaussian bumps
    (centres 380–780 nm, widths 20–80 nm), scaled into [0.02, 0.98]; 10 nm samples."""
    import evhsi_jax as ev

    rng = np.random.default_rng(seed)
    wl = np.arange(380.0, 781.0, 10.0)
    n = height * width
    pal = np.full((n, wl.size), 0.1)
    for _ in range(3):
        c = rng.uniform(380.0, 780.0, (n, 1))
        s = rng.uniform(20.0, 80.0, (n, 1))
        a = rng.uniform(0.0, 0.6, (n, 1))
        pal += a * np.exp(-0.5 * ((wl - c) / s) ** 2)
    pal = 0.02 + 0.96 * pal / pal.max(axis=1, keepdims=True)
    return ev.Scene(pal, wl, np.arange(n, dtype=np.int32).reshape(height, width))


def build_scene(name: str, height: int, width: int):
    import evhsi_jax as ev

    if name == "random":
        return random_scene(height, width)
    return ev.load_scene(name, (height, width))


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def profile_sweep(scene, rig, chunk_columns: int) -> dict:
    """Time the parts of one sweep by calling the simulator's own pieces (private
    modules: this is a diagnosis, not an API use)."""
    import jax
    import jax.numpy as jnp
    import jax.random as jr

    from evhsi_jax._base import stable_argsort_int
    from evhsi_jax._base._spectra import band_integrate_matrix
    from evhsi_jax._model._illumination import band_table
    from evhsi_jax._simulate import _capture as sim

    h, w = scene.height, scene.width
    if chunk_columns is None:
        kind = "cpu" if jax.default_backend() == "cpu" else "accelerator"
        chunk_columns = sim.CHUNK_COLUMNS[kind]
    chunk_columns = min(chunk_columns, w)
    offsets = np.asarray(rig.column_offsets(w), np.float64)
    thr_on, thr_off = sim.threshold_maps(rig, h, w, key=jr.key(0))
    n = rig.samples_per_sweep * sim.time_oversampling(rig)
    dt = float(rig.period_us) / n
    fine = band_table(rig)
    starts, length = sim._windows(rig, fine, offsets, n, dt, chunk_columns)
    bmat = band_integrate_matrix(scene.wavelengths_nm, rig.grid.fine_edges_nm)
    if bmat.shape[0] < bmat.shape[1]:
        tab = jnp.asarray(np.asarray(fine.values, np.float64) @ bmat.T, jnp.float32)
        pal = scene.palette
    else:
        tab, pal = fine.values, scene.palette @ bmat
    use_palette = pal.shape[0] < h
    pal_j = jnp.asarray(pal, jnp.float32)
    parts = dict(intensity=0.0, scan=0.0, to_host=0.0, extract=0.0)
    from evhsi_jax._base._numba import use_numba

    compiled = jax.default_backend() == "cpu" and use_numba()
    n_chunks = -(-w // chunk_columns)
    col_index = np.minimum(np.arange(n_chunks * chunk_columns), w - 1)
    col_index = col_index.reshape(n_chunks, chunk_columns)
    ts, ps = [], []
    # Chunk 0 twice: the first call compiles and is not counted.
    for i, ci in enumerate([0] + list(range(n_chunks))):
        cols = col_index[ci]
        lab = scene.labels[:, cols].T
        spectra = pal_j if use_palette else pal_j[jnp.asarray(lab)]
        t0 = time.perf_counter()
        log_i = sim._log_intensity_jit(
            rig,
            tab,
            fine.lo_nm,
            jnp.asarray((starts[ci] + np.arange(length)) * dt, jnp.float32),
            jnp.asarray(offsets[cols], jnp.float32),
            spectra,
            jnp.asarray(lab),
        )
        log_i.block_until_ready()
        t_mid = time.perf_counter()
        if compiled:  # the CPU path: the numba state machine emits the crossings
            from evhsi_jax._simulate._scan_jit import events_scan

            li = np.asarray(log_i)
            r0 = li[0].copy()
            _, _, t_ev, up_ev, n_ev = events_scan(
                li, np.asarray((starts[ci] + np.arange(length)) * dt, np.float32),
                thr_on[:, cols].T.reshape(-1).astype(np.float32),
                thr_off[:, cols].T.reshape(-1).astype(np.float32),
                np.float32(rig.refractory_us), r0,
                np.full(r0.shape, -1e9, np.float32), np.zeros(r0.shape, bool),
                rig.reset_mode == "release", np.zeros((1, 1), np.float32), False,
                li.size,
            )  # fmt: skip
            t_ev, up_ev = t_ev[:n_ev], up_ev[:n_ev]
            t1 = t2 = time.perf_counter()
        else:
            (fired, tc, up), _ = sim._trigger_scan_jit(
                rig,
                log_i,
                jnp.asarray((starts[ci] + np.arange(length)) * dt, jnp.float32),
                jnp.asarray(thr_on[:, cols].T.reshape(-1)),
                jnp.asarray(thr_off[:, cols].T.reshape(-1)),
                None,
                None,
            )
            fired.block_until_ready()
            t1 = time.perf_counter()
            if jax.default_backend() == "cpu":  # the XLA scan: dense arrays, nonzero
                fired, tc, up = np.asarray(fired), np.asarray(tc), np.asarray(up)
                t2 = time.perf_counter()
                step, pix = np.nonzero(fired)
                t_ev, up_ev = tc[step, pix], up[step, pix]
            else:  # gathered on the device, only the crossings come back ("to_host")
                _, _, t_ev, up_ev = sim._fired_events(fired, tc, up, on_host=False)
                t2 = time.perf_counter()
        ts.append(np.floor(t_ev).astype(np.int64))
        ps.append(up_ev)
        t3 = time.perf_counter()
        if i == 0:
            ts, ps = [], []
            continue
        parts["intensity"] += t_mid - t0
        parts["scan"] += t1 - t_mid
        parts["to_host"] += t2 - t1
        parts["extract"] += t3 - t2
    t0 = time.perf_counter()
    stable_argsort_int(np.concatenate(ts))  # as the simulator does
    parts["sort"] = time.perf_counter() - t0
    parts["window_samples"] = int(length)
    parts["scan_kind"] = "numba" if compiled else "xla"
    parts["chunks"] = int(n_chunks)
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in parts.items()}


def worker(args) -> dict:
    """Run one scene: cold run, warm runs; print the record as JSON."""
    import jax
    import jax.random as jr

    import evhsi_jax as ev

    h, w = args.size
    t0 = time.perf_counter()
    scene = build_scene(args.worker, h, w)
    rig = ev.Rig()
    build_s = time.perf_counter() - t0

    def run():
        t = time.perf_counter()
        events = ev.simulate(
            scene, rig, chunk_columns=args.chunk_columns, key=jr.key(0)
        )
        return time.perf_counter() - t, events

    cold_s, events = run()
    warm = [run()[0] for _ in range(args.repeats)]
    n = len(events)
    best = statistics.median(warm) if warm else cold_s
    rec = {
        "scene": args.worker,
        "path": "palette" if len(scene.palette) < h else "per-pixel",
        "spectra": int(len(scene.palette)),
        "height": h,
        "width": w,
        "sweeps": 1,
        "events": int(n),
        "events_per_pixel_per_sweep": round(n / (h * w), 2),
        "scene_build_s": round(build_s, 3),
        "cold_s": round(cold_s, 3),
        "warm_s": [round(v, 3) for v in warm],
        "median_s": round(best, 3),
        "min_s": round(min(warm), 3) if warm else None,
        "compile_s": round(max(cold_s - best, 0.0), 3),
        "mev_per_s": round(n / best / 1e6, 3),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        # The target is for the full sensor only.
        "meets_target": bool(best < TARGET_S) if (h, w) == (720, 1280) else None,
        "jax_backend": jax.default_backend(),
    }
    from _common import matmul_gflops

    rec["matmul_gflops"] = round(matmul_gflops(), 1)
    if args.profile:
        rec["profile_s"] = profile_sweep(scene, rig, args.chunk_columns)
    return rec


def machine() -> dict:
    import jax

    return {
        "cpu_count": os.cpu_count(),
        "affinity": len(os.sched_getaffinity(0))
        if hasattr(os, "sched_getaffinity")
        else None,
        "load_average_1m": round(os.getloadavg()[0], 2),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "memory_gb": round(
            os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1
        ),
    }


def table(records: list[dict]) -> str:
    head = (
        "| scene | path | size | events | ev/px/sweep | cold s | warm s (median, min) "
        "| compile s | Mev/s | peak RSS MB | ≤ 10 s |"
    )
    lines = [head, "|" + "---|" * 11]
    verdict = {True: "yes", False: "NO", None: "n/a (not full size)"}
    for r in records:
        lines.append(
            f"| {r['scene']} | {r['path']} ({r['spectra']} spectra) | "
            f"{r['height']}×{r['width']} | {r['events']:,} | "
            f"{r['events_per_pixel_per_sweep']} | {r['cold_s']} | "
            f"{r['median_s']}, {r['min_s']} | {r['compile_s']} | {r['mev_per_s']} | "
            f"{r['peak_rss_mb']} | {verdict[r['meets_target']]} |"
        )
    return "\n".join(lines)


def figure(path: Path, records: list[dict], full_size: bool) -> None:
    """Bars of the median sweep time per scene, split by part when profiled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    names = [f"{r['scene']}\n({r['path']})" for r in records]
    x = np.arange(len(records))
    ax.bar(x, [r["median_s"] for r in records], 0.6, color="0.85", label="whole sweep")
    parts = ("intensity", "scan", "extract", "sort")
    bottom = np.zeros(len(records))
    for part, colour in zip(parts, ("C0", "C1", "C2", "C3")):
        vals = np.array([r.get("profile_s", {}).get(part, 0.0) for r in records])
        if vals.any():
            ax.bar(x, vals, 0.3, bottom=bottom, color=colour, label=part)
            bottom += vals
    if full_size:
        ax.axhline(TARGET_S, color="k", ls="--", lw=1, label="target 10 s")
    ax.set_xticks(x, names)
    ax.set_ylabel("seconds per sweep")
    r0 = records[0]
    ax.set_title(f"simulate one sweep, {r0['height']}×{r0['width']}, paper rig")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HxW, got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=parse_size, default=(720, 1280), help="HxW pixels")
    p.add_argument("--repeats", type=int, default=3, help="warm runs per scene")
    p.add_argument("--scenes", default=",".join(SCENES), help="comma-separated")
    p.add_argument(
        "--chunk-columns", type=int, default=None, help="default: by device kind"
    )
    p.add_argument("--profile", action="store_true", help="time the parts of a sweep")
    p.add_argument("--out", type=Path, default=None, help="JSON path")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args)))
        return 0

    scenes = [s for s in args.scenes.split(",") if s]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        p.error(f"unknown scenes {unknown}; choose from {SCENES}")
    h, w = args.size
    command = "python experiments/bench_simulate.py " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )
    records = []
    for name in scenes:
        cmd = [
            sys.executable,
            __file__,
            "--worker",
            name,
            "--size",
            f"{h}x{w}",
            "--repeats",
            str(args.repeats),
        ]
        if args.chunk_columns is not None:
            cmd += ["--chunk-columns", str(args.chunk_columns)]
        cmd += ["--profile"] if args.profile else []
        print(f"[{name}] running {h}×{w}…", file=sys.stderr, flush=True)
        out = subprocess.run(cmd, capture_output=True, text=True)
        if out.returncode:
            sys.stderr.write(out.stderr)
            return out.returncode
        records.append(json.loads(out.stdout.strip().splitlines()[-1]))
    info = machine()
    result = {
        "command": command.strip(),
        "machine": info,
        "rig": "Rig() defaults (paper simulation)",
        "target_s_per_full_sweep": TARGET_S,
        "chunk_columns": args.chunk_columns,
        "records": records,
    }
    out = args.out or RESULTS / (
        "bench_simulate.json"
        if (h, w) == (720, 1280)
        else f"bench_simulate_{h}x{w}.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    figure(out.with_suffix(".png"), records, (h, w) == (720, 1280))
    print(f"`{result['command']}`  ")
    print(
        f"machine: {info['cpu_count']} CPUs ({info['processor']}), "
        f"{info['memory_gb']} GB, {info['platform']}, jax {info['jax']} "
        f"({info['backend']}), load {info['load_average_1m']}\n"
    )
    print(table(records))
    for r in records:
        print(
            f"{r['scene']}: float32 matmul {r.get('matmul_gflops')} GFLOP/s (same run)"
        )
        if "profile_s" in r:
            print(f"\nprofile {r['scene']}: {r['profile_s']}")
    print(f"\nwrote {out} and {out.with_suffix('.png').name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
