"""The photoreceptor pass's rows on one GPU: the CUDA kernel of
`evhsi_jax/_reconstruct/_cuda_lowpass.py` against JAX's rows (`_problem._lowpass_rows`,
an associative scan over each pixel's whole time grid), and the box-QP kernel's
solve of the same chunk beside them.

Setup: one sweep of the ColorChecker at `--size` from the `realistic` preset (sensor
effects on: threshold noise 0.01, jitter 5 µs, a 10 kHz photoreceptor, noise events,
hot pixels, ON/OFF correlation, latency, a 0.5 px PSF, skewed band, curvature, rate
jitter), simulated on the device, screened and grouped as `reconstruct` does on an
accelerator, its true rig as the calibration (so the noise model with the
photoreceptor). The first chunk (`--chunk` pixels, the GPU's default 2^17) is taken;
its first rows are formed and solved (the kernel), then the photoreceptor rows at
that answer are timed (medians of `--repeats` in one process, after a first call):

- `kernel_s`: the CUDA kernel on the whole chunk;
- `jax_s`: JAX's rows on the first `--jax-pixels` pixels (the whole chunk's
  `(pixels, grid, M+1)` scan does not fit an H100's memory at JAX's default pool),
  and the kernel on those same pixels (`kernel_sub_s`), with the largest difference
  between the two rows (relative to the rows' largest entry);
- `solve_s`: one solve of the chunk by the box-QP kernel (rows to answers).

    python experiments/bench_gpu_lowpass.py [--size 720x1280] [--chunk 131072]
        [--jax-pixels 16384] [--repeats 5] [--out PATH]

Needs a CUDA GPU with numba's CUDA target (the `device` tool's machines have both);
writes `experiments/results/bench_gpu_lowpass.json`.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from _common import device_header, median_time, write_json

import evhsi_jax as ev
from evhsi_jax._reconstruct import _cuda_kernel as ck
from evhsi_jax._reconstruct import _cuda_lowpass as cl
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct._pixels import DeviceLists, bucket_plan
from evhsi_jax._reconstruct._problem import spectral_prior_matrix


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--chunk", type=int, default=131072)
    ap.add_argument("--jax-pixels", type=int, default=16384)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="experiments/results/bench_gpu_lowpass.json")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    report = device_header(h, w)
    rig = ev.Rig(sensor="realistic")
    scene = ev.load_scene("colorchecker", (h, w))
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)
    noise = pipe.noise_model(rig)
    keep, _, _, _ = pipe._screen_mask(events, rig, 0, noise, 1, None)
    lists = DeviceLists(events, 0, keep)
    sel, k, size = bucket_plan(lists.counts, args.chunk, args.chunk, args.chunk // 4)[0]
    per_pixel = jax.device_put(tuple(np.asarray(a, np.float32).reshape(-1) for a in (
        np.zeros(h * w), np.asarray(rig.column_offsets(w)), info.threshold_on,
        info.threshold_off)))  # fmt: skip
    _, _, px = lists.batch(sel, k, size, *per_pixel, np.float32)
    table = pipe.channel_table(rig)
    cfg = pipe.ProblemConfig()
    noise_j = jnp.asarray(noise, jnp.float32)
    rows, n = jax.block_until_ready(pipe._chunk_rows(rig, table, cfg, px, 1, noise_j))
    prior = spectral_prior_matrix(table.values.shape[1], cfg.m_start_frac, cfg.spec_kind)

    def solve():
        out = ck.solve_rows(rows, n, prior, cfg.ridge, 1e-6, 48)
        return out

    x = ck.to_jax(solve()[0])
    par, g_n = cl.lowpass_params(rig, table, noise, 1)
    report.update({"chunk_pixels": int(size), "slots": int(k), "grid_points": g_n,
                   "events_in_chunk": int(np.asarray(n).sum())})  # fmt: skip

    def kernel(p=px, nn=n, lw=rows.log_weight, xx=x):
        out = cl.lowpass_rows(p, nn, lw, xx, table.values, par, g_n)
        ck.synchronize()
        return out

    report["kernel_s"] = median_time(kernel, args.repeats)
    report["solve_s"] = median_time(lambda: (solve(), ck.synchronize()), args.repeats)
    j = min(args.jax_pixels, int(size))
    sub = jax.tree.map(lambda a: a[:j], px)
    n_sub, lw_sub, x_sub = n[:j], rows.log_weight[:j], x[:j]
    jax.block_until_ready((sub, n_sub, lw_sub, x_sub))

    def jax_rows():
        r, _ = pipe._chunk_rows(rig, table, cfg, sub, 1, noise_j, x_sub)
        return jax.block_until_ready(r.events)

    report["jax_pixels"] = j
    report["jax_s"] = median_time(jax_rows, args.repeats)
    report["kernel_sub_s"] = median_time(
        lambda: kernel(sub, n_sub, lw_sub, x_sub), args.repeats
    )
    ref = np.asarray(jax_rows())
    got = np.asarray(ck.to_jax(kernel(sub, n_sub, lw_sub, x_sub)))
    report["max_abs_diff_rel"] = float(np.abs(got - ref).max() / np.abs(ref).max())
    report["kernel_px_per_s"] = size / report["kernel_s"]
    report["jax_px_per_s"] = j / report["jax_s"]
    print({k: v for k, v in report.items() if "times" not in k}, flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
