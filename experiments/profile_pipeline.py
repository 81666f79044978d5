"""Where the reconstruction's time goes, stage by stage (a diagnosis, not an API use).

Setup: one sweep of the ColorChecker at `--size` (default 96×144), paper rig, ideal
sensor, nominal thresholds, float32, on JAX's default device; with `--noise`, a sensor
with threshold noise 0.01 and 5 µs jitter reconstructed with that noise model (its
weighted rows and dark-channel prior; no reweighting in the timed stages). Timed, each
the median of `--repeats` warm runs in this process:

- host: screening (`screen_events`) and grouping by pixel (`group_pixels`), with the
  numba kernels and with the NumPy reference;
- device, per chunk and summed over the image's chunks (batch sizes as `reconstruct`
  picks them): forming the weighted rows of every pixel (`pixel_system(...,
  return_rows=True)`), their Gram matrices (`system_from_rows`), and the exact solve
  (`active_set_batch`) of the assembled systems, with the number of active-set steps;
- the same run's float32 matmul GFLOP/s (`_common.matmul_gflops`).

    python experiments/profile_pipeline.py [--size 96x144] [--repeats 3]
        [--host-backends numpy,numba] [--noise]

Every device stage is traced under the reconstruction's matmul precision
(`_pipeline.MATMUL_PRECISION`: full float32 on a GPU, as `reconstruct` runs them).

Prints one JSON object (nothing is written).
"""

from __future__ import annotations

import argparse
import json

import equinox as eqx
import jax
import jax.random as jr
import numpy as np
from _common import matmul_gflops, median_time

import evhsi_jax as ev
from evhsi_jax._base._numba import numba_available, use_backend
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct import _solvers
from evhsi_jax._reconstruct._pixels import PixelEvents, group_pixels
from evhsi_jax._reconstruct._problem import (
    ProblemConfig,
    pixel_system,
    system_from_rows,
)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--host-backends", default="numpy,numba",
        help="host bookkeeping timed with these (numpy: the reference, slow on large "
        "captures)",
    )  # fmt: skip
    ap.add_argument("--noise", action="store_true",
                    help="threshold noise 0.01, jitter 5 µs, and their noise model")  # fmt: skip
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    rig = ev.Rig(threshold_noise=0.01, timestamp_jitter_us=5.0) if args.noise else ev.Rig()
    noise = pipe.noise_model(rig)
    noise_j = None if noise is None else jax.numpy.asarray(noise, jax.numpy.float32)
    events = ev.simulate(ev.load_scene("colorchecker", (h, w)), rig, key=jr.key(0))
    chunk, sub = pipe.batch_sizes(None, None)
    out = {"size": [h, w], "events": len(events), "batch_sizes": [chunk, sub],
           "noise_model": None if noise is None else [float(v) for v in noise]}  # fmt: skip
    out["matmul_gflops"] = matmul_gflops()
    wanted = args.host_backends.split(",")
    for backend in [b for b in wanted if b != "numba" or numba_available()]:
        with use_backend(backend):
            screen = median_time(
                lambda: pipe.screen_events(events, rig, 0, noise, 1, None)[2],
                args.repeats,
            )
            screened = pipe.screen_events(events, rig, 0, noise, 1, None)[0]
            group = median_time(
                lambda: len(
                    group_pixels(
                        screened,
                        t_start_us=0,
                        chunk_pixels=chunk,
                        min_chunk=sub, merge_below=chunk // 4,
                    )[0]
                ),  # fmt: skip
                args.repeats,
            )
        out[f"host_{backend}_s"] = {"screen": screen, "group": group}
    batches, _, _ = group_pixels(
        screened, t_start_us=0, chunk_pixels=chunk, min_chunk=sub,
        merge_below=chunk // 4,
    )
    table = pipe.channel_table(rig)
    cfg = ProblemConfig()
    offs = np.asarray(rig.column_offsets(w), np.float32)

    def split(tree, n):
        return jax.tree.map(
            lambda a: a.reshape((a.shape[0] // n, n) + a.shape[1:]), tree
        )

    @eqx.filter_jit
    def rows(px):
        def one(p):
            return pixel_system(rig, table, cfg, p, 1, noise=noise_j, return_rows=True)

        with jax.default_matmul_precision(pipe.MATMUL_PRECISION):
            return jax.lax.map(jax.vmap(one), split(px, sub))

    @eqx.filter_jit
    def gram(r):
        with jax.default_matmul_precision(pipe.MATMUL_PRECISION):
            return jax.lax.map(
                jax.vmap(lambda one: system_from_rows(cfg, one)[:2]), r
            )

    @jax.jit
    def solve(q, v):
        def one(a):
            return _solvers.active_set_batch(a[0], a[1], tol=1e-6, max_iters=48)

        with jax.default_matmul_precision(pipe.MATMUL_PRECISION):
            x, kkt, steps = jax.lax.map(one, (q, v))
        return x, steps

    parts = {"rows": 0.0, "gram": 0.0, "solve": 0.0, "active_set_steps": 0}
    for b in batches:
        arrays = (
            np.where(b.mask, b.t_us, 0.0).astype(np.float32),
            b.polarity.astype(np.int32),
            b.mask,
            offs[b.column],
            np.full(b.pixel.shape, float(rig.threshold_on), np.float32),
            np.full(b.pixel.shape, float(rig.threshold_off), np.float32),
            np.zeros(b.pixel.shape, np.float32),
        )
        px = PixelEvents(*jax.device_put(arrays))
        r = rows(px)
        q, v = gram(r)
        parts["rows"] += median_time(lambda px=px: rows(px), args.repeats)
        parts["gram"] += median_time(lambda r=r: gram(r), args.repeats)
        parts["solve"] += median_time(lambda q=q, v=v: solve(q, v), args.repeats)
        parts["active_set_steps"] += int(np.sum(solve(q, v)[1]))
    out["device_s"] = parts
    out["padded_pixels"] = int(sum(b.pixel.size for b in batches))
    out["pixels_with_events"] = int(sum((b.pixel >= 0).sum() for b in batches))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
