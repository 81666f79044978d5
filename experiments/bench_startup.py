"""Whole-process time of `evhsi reconstruct` (and `evhsi calibrate`) with an empty and
then a filled persistent compilation cache: what a user waits for at the prompt.

Simulates a ColorChecker capture and a gray chart (paper rig) of `--size`, then runs
each command `--repeats` times in fresh processes: the first run with an empty cache
folder (compiles everything), the rest with the cache it filled. Prints the times
(medians of the warm runs) and this machine's float32 matmul GFLOP/s.

Both caches start empty: JAX's (`EVHSI_CACHE_DIR`) and numba's (`NUMBA_CACHE_DIR`, a
fresh folder: the host kernels and, with `--backends cuda`, the CUDA kernel). Each
command runs first with the cache off — JAX's cache and the CUDA kernel's
(`EVHSI_CUDA_CACHE=0`) off, numba's folder holding only what the capture's simulation
stored, so that run also compiles the command's numba kernels, as a fresh install's
first process does, and leaves them in the folder — then with JAX's cache empty
("first run"), then `--repeats` times with it filled.
`--backends jax,cuda` times `evhsi reconstruct --backend B` for each (a GPU).

    .venv/bin/python experiments/bench_startup.py [--size 96x144] [--repeats 3]
        [--backends default|auto,jax,fused,cuda]
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

import numpy as np

EVHSI = [sys.executable, "-m", "evhsi_jax.cli"]


def matmul_gflops() -> float:
    code = (
        "import time, jax, jax.numpy as jnp, numpy as np\n"
        "a = jnp.ones((1024, 1024), jnp.float32); f = jax.jit(lambda x: x @ x)\n"
        "f(a).block_until_ready(); t = []\n"
        "for _ in range(5):\n"
        "    s = time.perf_counter(); f(a).block_until_ready(); "
        "t.append(time.perf_counter() - s)\n"
        "print(2 * 1024**3 / float(np.median(t)) / 1e9)\n"
    )
    return float(subprocess.run([sys.executable, "-c", code], capture_output=True,
                                text=True, check=True).stdout)  # fmt: skip


def timed(argv, env) -> float:
    t = time.perf_counter()
    subprocess.run([*EVHSI, *map(str, argv)], env=env, check=True, capture_output=True)
    return time.perf_counter() - t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", default="96x144")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--jobs", default="reconstruct,calibrate", help="which commands")
    p.add_argument("--backends", default="default",
                   help="reconstruct's --backend values to time (default: none given)")
    p.add_argument("--json", default="experiments/results/bench_startup.json")
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        env = {**os.environ, "EVHSI_CACHE_DIR": str(d / "cache"),
               "NUMBA_CACHE_DIR": str(d / "numba")}  # fmt: skip
        off = {**env, "EVHSI_CACHE_DIR": "off", "EVHSI_CUDA_CACHE": "0"}
        subprocess.run([*EVHSI, "simulate", "--scene", "colorchecker", "--size", a.size,
                        "--out", d / "cc.raw", "--quiet"], check=True, env=off)  # fmt: skip
        if "calibrate" in a.jobs.split(","):
            subprocess.run([*EVHSI, "simulate", "--scene", "gray-chart", "--size",
                            a.size, "--sweeps", "2", "--out", d / "gray.npz",
                            "--quiet"], check=True, env=off)  # fmt: skip
        (d / "cal.json").write_text("{}")
        rec = ["reconstruct", d / "cc.raw", "--calib", d / "cal.json", "--out",
               d / "cube.npz", "--quiet"]  # fmt: skip
        jobs = {}
        for b in a.backends.split(","):
            name = "reconstruct" if b == "default" else f"reconstruct --backend {b}"
            jobs[name] = rec if b == "default" else [*rec, "--backend", b]
        jobs["calibrate"] = ["calibrate", d / "gray.npz", "--out", d / "c.json"]
        out = {"size": a.size, "matmul_gflops": matmul_gflops()}
        for name, argv in jobs.items():
            if name.split()[0] not in a.jobs.split(","):
                continue
            no_cache = timed(argv, off)
            first = timed(argv, env)
            warm = [timed(argv, env) for _ in range(a.repeats)]
            out[name] = {
                "no_cache_s": round(no_cache, 2),
                "first_run_s": round(first, 2),
                "cached_median_s": round(float(np.median(warm)), 2),
                "cached_runs_s": [round(v, 2) for v in warm],
            }
            print(name, out[name], flush=True)
        # What numba kept (the CUDA kernel's entries name `make_kernel`'s closure).
        out["numba_cache_files"] = sorted(
            f.name for f in (d / "numba").rglob("*") if f.is_file()
        )  # fmt: skip
    print(json.dumps(out, indent=1))
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
