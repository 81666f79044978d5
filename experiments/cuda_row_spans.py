"""How much work the bands' trim takes off the CUDA kernel, counted on a CPU.

The `cuda` backend's kernel forms each pixel's Q from the nonzero span of each of
JAX's dense rows and factorises it over Q's envelope; its work per pixel grows with
the spans (Q's formation: Σ span² over the rows; the factorisation: Σ over Q's rows
of their envelope length²). Since the eighteenth session the backend forms the rows
from `channel_table(rig).trimmed()` (each band's entries below 1e-7 of its peak set
to zero, as the fused CPU kernel's spans). This script counts both sums with the
untrimmed and the trimmed table: a proxy for the kernel's arithmetic, not a timing
(no GPU needed; `bench_gpu.py` times it where a device is lent).

Setup: one sweep of the ColorChecker at `--size` (default 24×36), paper rig with the
`ideal` and the `realistic` sensor presets, the rig's global thresholds, the rows as
the `cuda` backend forms them (`_pipeline._chunk_rows`, float32, without the
photoreceptor pass), chunks of 256 pixels.

    .venv/bin/python experiments/cuda_row_spans.py [--size 24x36] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax.numpy as jnp
import jax.random as jr
import numpy as np

import evhsi_jax as ev
from evhsi_jax._reconstruct import ProblemConfig, group_pixels
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct._fused import row_spans


def work(rig, table, batches, offsets, noise) -> dict:
    """Mean row span, Σ span² and Σ envelope² per pixel of the rows from `table`."""
    s1 = s2 = env = 0.0
    n_rows = n_px = 0
    big = np.full(1 << 20, 0.0)
    for b in batches:
        valid = b.pixel >= 0
        px = pipe._device_pixels(
            b.t_us, b.polarity, b.mask, b.pixel, b.column, np.zeros(b.pixel.shape),
            offsets, big + float(rig.threshold_on), big + float(rig.threshold_off),
            np.float32,
        )  # fmt: skip
        rows, _ = pipe._chunk_rows(rig, table, ProblemConfig(), px, 1, noise)
        r = np.concatenate(
            [np.asarray(rows.events)[..., :-1], np.asarray(rows.drift)[..., :-1]], axis=1
        )[valid]
        lo, hi = row_spans(r != 0)
        has = hi > lo
        m = r.shape[-1]
        span = np.where(has, hi - lo, 0)
        s1 += span.sum()
        s2 += (span * span).sum()
        n_rows += has.sum()
        n_px += valid.sum()
        for p in range(r.shape[0]):  # Q's envelope: the first column reaching row i
            first = np.arange(m)
            for a, z, ok in zip(lo[p], hi[p], has[p]):
                if ok:
                    first[a:z] = np.minimum(first[a:z], a)
            env += ((np.arange(m) - first + 1) ** 2).sum()
    return {"mean_row_span": s1 / n_rows, "sum_span2_per_px": s2 / n_px,
            "sum_envelope2_per_px": env / n_px}  # fmt: skip


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="24x36")
    ap.add_argument("--out", default="results/cuda_row_spans.json")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    out = {"size": [h, w]}
    for sensor in ("ideal", "realistic"):
        rig = ev.Rig(sensor=sensor)
        events = ev.simulate(ev.load_scene("colorchecker", (h, w)), rig, sweeps=1,
                             key=jr.key(0))  # fmt: skip
        noise = pipe.noise_model(rig)
        t0 = int(events.trigger_t_us[0])
        kept, _, _ = pipe.screen_events(events, rig, t0, noise, 1, None)
        batches, _, _ = group_pixels(kept, t_start_us=t0, chunk_pixels=256)
        offsets = np.asarray(rig.column_offsets(w))
        noise_j = None if noise is None else jnp.asarray(noise, jnp.float32)
        table = pipe.channel_table(rig)
        rows = {}
        for name, tab in (("untrimmed", table), ("trimmed", table.trimmed())):
            rows[name] = work(rig, tab, batches, offsets, noise_j)
            r = rows[name]
            print(f"{sensor:9s} {name:9s}: mean row span {r['mean_row_span']:.1f}, "
                  f"Σ span² {r['sum_span2_per_px']:.0f} and Σ envelope² "
                  f"{r['sum_envelope2_per_px']:.0f} per pixel")  # fmt: skip
        out[sensor] = rows
    path = Path(__file__).parent / args.out
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
