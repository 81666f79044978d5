"""Shared helpers of the studies (public API only): capture, reconstruct, save."""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

import jax
import jax.random as jr
import numpy as np

import evhsi_jax as ev

OUT = Path(__file__).parent / "results"
ROOT = Path(__file__).resolve().parent.parent


def source_at(rev: str | None, path: str) -> str:
    """The text of the repository file `path` at git revision `rev` (None: the
    working tree), for the studies that time two revisions in one process."""
    if rev is None:
        return (ROOT / path).read_text()
    return subprocess.run(
        ["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True,
        text=True,
    ).stdout  # fmt: skip


def median_time(fn, repeats: int) -> float:
    """Median wall time of `repeats` calls of `fn` after one untimed call (compilation),
    each waited for (`jax.block_until_ready`; host results pass through)."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def matmul_gflops(n: int = 1024, repeats: int = 5) -> float:
    """This machine's float32 matmul rate through JAX right now (median of
    `repeats`), printed beside every timing so that runs on different machines
    compare."""
    a = jax.numpy.ones((n, n), jax.numpy.float32)
    f = jax.jit(lambda x: x @ x)
    f(a).block_until_ready()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f(a).block_until_ready()
        times.append(time.perf_counter() - t)
    return 2 * n**3 / float(np.median(times)) / 1e9


def device_header(h: int, w: int) -> dict:
    """The head of a device benchmark's report: the image size, the device kind, JAX's
    version and the device's float32 matmul rate (8192² on an accelerator, 1024² on
    a CPU) measured now."""
    dev = jax.devices()[0]
    return {
        "size": [h, w],
        "device": getattr(dev, "device_kind", str(dev)),
        "jax": jax.__version__,
        "matmul_gflops_f32": matmul_gflops(
            1024 if jax.default_backend() == "cpu" else 8192
        ),
    }


def machine() -> str:
    return (
        f"{os.cpu_count()} CPU ({platform.processor() or platform.machine()}), "
        f"jax {jax.__version__}, {jax.devices()[0].platform}"
    )


def white_response(rig, centres_nm):
    """A(λc): a white pixel's band light with the band centred at λc (peak 1 over λc).
    Where it is below the constant light c a feature makes no events on its own: the
    rainbow and realism studies split their metrics by A(λc) ≥ c."""
    tab = ev.forward.band_table(rig)
    lam = np.asarray(centres_nm, np.float32)
    return np.asarray(ev.forward.lookup(tab, lam)).sum(axis=1)


def capture(scene_name, size, *, rig=None, sweeps=1, seed=0):
    """Simulate a built-in scene; returns (rig, scene, events, sim_info, truth)."""
    rig = rig or ev.Rig()
    scene = ev.load_scene(scene_name, size)
    events, info = ev.simulate(
        scene, rig, sweeps=sweeps, key=jr.key(seed), return_info=True
    )
    return rig, scene, events, info, scene.truth_cube(rig.grid)


def timed_reconstruct(events, rig, info=None, **kw):
    """Reconstruct (with the sensor's per-pixel thresholds if `info` is given)."""
    if info is not None:
        kw.update(
            threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off
        )
    t0 = time.perf_counter()
    cube = ev.reconstruct(events, rig, **kw)
    return cube, time.perf_counter() - t0


def save(name: str, payload: dict, fig=None):
    """Write results/<name>.json (and .png from a matplotlib figure)."""
    OUT.mkdir(exist_ok=True)
    payload = {"machine": machine(), **payload}
    (OUT / f"{name}.json").write_text(json.dumps(payload, indent=1, default=_jsonable))
    if fig is not None:
        fig.savefig(OUT / f"{name}.png", dpi=110)
    print(f"wrote {OUT / name}.json" + (" and .png" if fig is not None else ""))


def write_json(path, report: dict):
    """Write `report` to `path` (a results file a script was told to write; its
    folder made), and say so."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2, default=_jsonable))
    print("wrote", out)


def _jsonable(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v))


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
