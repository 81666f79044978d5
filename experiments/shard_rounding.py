"""Where a sharded reconstruction differs from the plain one (a diagnostic, no figure).

Setup: the `mixed` dynamic scene, 6x12 pixels, 2 sweeps, paper rig, sub-batch 1. The
plain (unsharded) run is repeated with chunks of 4, 16 and 64 pixels; the sharded run on
a mesh of all devices with per-device chunks of 1, 4 and 16. Each is compared with the
plain run at chunk 16 (max absolute difference of the reflectance cube). Run with
several CPU devices, set before jax is imported:

    XLA_FLAGS=--xla_force_host_platform_device_count=4 python experiments/shard_rounding.py
    XLA_FLAGS="--xla_force_host_platform_device_count=4 --xla_cpu_multi_thread_eigen=false" \\
        python experiments/shard_rounding.py --tag no_eigen_threads

Writes results/shard_rounding[_TAG].json.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import jax
import jax.random as jr
import numpy as np

import evhsi_jax as ev


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tag", default="")
    args = p.parse_args()
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import save

    rig = ev.Rig()
    scenes = ev.forward.dynamic_scene("mixed", (6, 12), sweeps=2)
    events = ev.simulate(scenes, rig, sweeps=2, chunk_columns=4, key=jr.key(1))
    plain = {
        c: ev.reconstruct(events, rig, chunk_pixels=c, sub_batch=1) for c in (4, 16, 64)
    }
    ref = plain[16]
    out = {
        "command": "XLA_FLAGS="
        + os.environ.get("XLA_FLAGS", "")
        + " python experiments/shard_rounding.py"
        + (f" --tag {args.tag}" if args.tag else ""),
        "devices": len(jax.devices()),
        "plain_max_abs_diff": {
            c: float(np.abs(v - ref).max()) for c, v in plain.items()
        },
        "sharded_max_abs_diff": {},
    }
    if len(jax.devices()) > 1:
        mesh = ev.sharding.pixel_mesh()
        for c in (1, 4, 16):
            cube = ev.reconstruct(events, rig, chunk_pixels=c, sub_batch=1, mesh=mesh)
            out["sharded_max_abs_diff"][c] = float(np.abs(cube - ref).max())
    print(out)
    save("shard_rounding" + (f"_{args.tag}" if args.tag else ""), out)


if __name__ == "__main__":
    main()
