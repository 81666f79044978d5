"""One full-sensor sweep on whatever device JAX runs on (designed for one GPU).

Setup: the paper rig (`Rig()`), one sweep of the ColorChecker at `--size` (default
720×1280), simulated on the device, then reconstructed with `ev.reconstruct` (solver
`auto`, backend `jax`; `--backends cuda` adds the CUDA kernel's whole call), float32,
the sensor's true per-pixel thresholds as after a calibration, batch sizes by device
kind: `evhsi_jax.reconstruction.batch_sizes`). Reported, each the median
of `--repeats` warm runs in this process after one cold run (compilation):

- `simulate`: `ev.simulate` of the sweep (events back on the host);
- `reconstruct`: the whole `ev.reconstruct` call (events in host memory → cube in host
  memory; on an accelerator the events are grouped by pixel there,
  `_pipeline.DEVICE_GROUPING`), the same call with the host's grouping, and its
  parts: screening on the host, grouping on the host (numba) or on the device
  (`DeviceLists`: transfer, sort, batches), and the device work (assembly + solve of
  every chunk, inputs already on the device);
- the same with the noise-aware path (a calibration saying threshold noise 0.01 and
  jitter 5 µs: weighted rows, Huber reweighting) on the same events;
- `--cases realistic`: the path a real rig's calibration selects, on a capture with the
  sensor effects on (the `realistic` preset: threshold noise, jitter, a 10 kHz
  photoreceptor, noise events, hot pixels, ON/OFF correlation, latency, a 0.5 px PSF,
  a skewed band, sweep curvature and rate jitter; simulated on the device), the true
  rig as the calibration (its noise model, photoreceptor pass and deblurring) and its
  true per-pixel thresholds; SAM against the sharp truth (whole calls only);
- accuracy: SAM/PSNR to the truth, and the float32 cube against a float64 solve of
  the same events (share of pixels within 0.1° SAM);
- the device work of the ideal path with other batch sizes (`--batch-variants`,
  `CHUNKxSUB,...`: does a larger or smaller step fill the device better?);
- the device's float32 matmul rate (8192² on a GPU, 1024² on a CPU) in the same run;
- `--channels N`: every case reconstructed on N channels (`Rig.with_channels`; the
  captures are the 72-channel rig's), its metrics on the cube interpolated onto the 72
  truth channels (README, Performance, "Fewer channels").

    python experiments/bench_gpu.py [--size 720x1280] [--repeats 3] [--out PATH]
        [--cases ideal,noise,realistic] [--batch-variants 65536x65536,262144x262144]
        [--backends jax,cuda] [--base-backend jax|cuda] [--whole-only] [--no-float64] [--profile N]
        [--channels N]

Writes `experiments/results/bench_gpu.json` (or `--out`). On a CPU use a small
`--size` (the full sensor takes minutes there); the GPU figures in the README were
measured with the `device` tool on one H100.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import platform
import pstats
import statistics
import time

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from _common import matmul_gflops, write_json

import evhsi_jax as ev
from evhsi_jax._model import band_table
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct._pixels import (
    DeviceLists,
    bucket_plan,
    group_pixels,
)


def timed(fn, repeats):
    """(result, cold seconds, warm times)."""
    t = time.perf_counter()
    out = fn()
    cold = time.perf_counter() - t
    warm = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        warm.append(time.perf_counter() - t)
    return out, cold, warm


def device_parts(events, rig, maps, repeats, chunk=None, sub=None):
    """Host (screen + group) and device (assembly + solve) time of one reconstruction,
    timed apart: the chunks' inputs are put on the device before the device clock
    starts. `chunk`, `sub`: batch sizes (default: `batch_sizes`' for the device)."""
    noise = pipe.noise_model(rig)
    chunk, sub = pipe.batch_sizes(chunk, sub)

    def host():
        screened, _, _ = pipe.screen_events(events, rig, 0, noise, 1, None)
        return group_pixels(  # as `reconstruct` cuts them
            screened, t_start_us=0, chunk_pixels=chunk, min_chunk=sub,
            merge_below=chunk // 4,
        )  # fmt: skip

    (batches, _, _), _, host_t = timed(host, repeats)
    screened = pipe.screen_events(events, rig, 0, noise, 1, None)[0]
    _, _, screen_t = timed(
        lambda: pipe.screen_events(events, rig, 0, noise, 1, None), repeats
    )
    dtype = np.dtype(rig.fwhm_nm.dtype)
    z = np.zeros(events.width * events.height)
    per_pixel = jax.device_put(
        tuple(
            a.astype(dtype)
            for a in (z, np.asarray(rig.column_offsets(events.width)), *maps)
        )
    )  # fmt: skip
    per_pixel = tuple(a.reshape(-1) for a in per_pixel)

    def device_grouping():  # what reconstruct does on an accelerator
        lists = DeviceLists(screened, 0)
        plan = bucket_plan(lists.counts, chunk, sub, chunk // 4)
        out = [lists.batch(sel, k, size, *per_pixel, dtype) for sel, k, size in plan]
        return jax.block_until_ready(out)

    _, _, dev_group_t = timed(device_grouping, repeats)
    dtype = rig.fwhm_nm.dtype
    offs = np.asarray(rig.column_offsets(events.width), np.float64)
    on, off = (np.asarray(m, np.float64).reshape(-1) for m in maps)
    pxs = []
    for b in batches:  # as reconstruct puts each batch on the device
        pix = np.where(b.pixel >= 0, b.pixel, 0)
        pxs.append(pipe._device_pixels(
            b.t_us, b.polarity, b.mask, pix, b.column, np.zeros(pix.shape), offs, on,
            off, np.dtype(dtype),
        ))  # fmt: skip
    table = band_table(rig).channels(rig.grid.sub)
    spec = pipe.solver_spec("auto")
    noise_j = None if noise is None else jnp.asarray(noise, dtype)

    def device():
        outs = [
            pipe._solve_chunk(
                rig, table, pipe.ProblemConfig(), spec, min(sub, p.t_us.shape[0]), p, 1,
                noise_j,
            )
            for p in pxs
        ]  # fmt: skip
        return jax.block_until_ready(outs)

    _, cold, dev_t = timed(device, repeats)
    return {
        "host_screen_group_s": statistics.median(host_t),
        "host_screen_s": statistics.median(screen_t),
        "device_group_s": statistics.median(dev_group_t),
        "device_assemble_solve_s": statistics.median(dev_t),
        "device_cold_s": cold,
        "device_times_s": dev_t,
        "chunks": [list(p.t_us.shape) for p in pxs],
    }


def profiled(fn, n):
    """cProfile of one call of `fn`: the `n` costliest functions by their own time and
    by their time with callees, as text lines (waits for the device show up in the
    host call that waits)."""
    prof = cProfile.Profile()
    prof.runcall(fn)
    out = {}
    for key in ("tottime", "cumulative"):
        buf = io.StringIO()
        pstats.Stats(prof, stream=buf).sort_stats(key).print_stats(n)
        out[key] = [ln for ln in buf.getvalue().splitlines() if ln.strip()]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="experiments/results/bench_gpu.json")
    ap.add_argument("--cases", default="ideal,noise")
    ap.add_argument("--batch-variants", default="")
    ap.add_argument(
        "--backends", default="", help="also time the whole call with these (jax,cuda)"
    )
    ap.add_argument(
        "--base-backend",
        default="jax",
        help="the backend of each case's first whole call (jax, or cuda to skip JAX's)",
    )
    ap.add_argument(
        "--whole-only",
        action="store_true",
        help="time the whole calls only (no parts, no host grouping)",
    )
    ap.add_argument(
        "--no-float64", action="store_true", help="leave out the float64 check"
    )
    ap.add_argument(
        "--channels", type=int, default=None, metavar="N",
        help="reconstruct N channels (Rig.with_channels) from captures of the 72-channel "
        "rig; metrics on the cube interpolated onto the 72 truth channels",
    )  # fmt: skip
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="cProfile one more warm whole call per backend: its N "
                         "costliest functions (own time, and with callees)")  # fmt: skip
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)

    def solved_by(r):  # the rig a case reconstructs with (captures: the 72-channel rig)
        return r if args.channels is None else r.with_channels(args.channels)

    dev = jax.devices()[0]
    report = {
        "size": [h, w],
        "backend": jax.default_backend(),
        "device": getattr(dev, "device_kind", str(dev)),
        "jax": jax.__version__,
        "host": platform.processor() or platform.machine(),
        "batch_sizes": list(pipe.batch_sizes(None, None)),
        "channels": args.channels or 72,
        # default precision (TF32 on a recent GPU)
        "matmul_gflops_f32": [
            matmul_gflops(1024 if jax.default_backend() == "cpu" else 8192)
        ],
    }
    rig = ev.Rig()
    report["auto_backend"] = (
        "cuda"
        if pipe._use_cuda(
            "auto", False, pipe.solver_spec("auto"), pipe.ProblemConfig(), rig, None
        )  # fmt: skip
        else "jax or fused"
    )
    print(report, flush=True)
    scene = ev.load_scene("colorchecker", (h, w))
    truth = scene.truth_cube(rig.grid)

    to_truth = (  # the reconstruction's channels onto the truth's 72
        None
        if args.channels is None
        else ev.forward.resample_matrix(solved_by(rig).wavelengths_nm, rig.wavelengths_nm)
    )

    def score(cube):  # SAM/PSNR on the truth's 72 channels
        cube = np.asarray(cube)
        return ev.evaluate(cube if to_truth is None else cube @ to_truth.T, truth)

    def sim():
        return ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)

    (events, info), cold, warm = timed(sim, args.repeats)
    report["simulate"] = {
        "cold_s": cold,
        "median_s": statistics.median(warm),
        "times_s": warm,
        "events": len(events),
    }
    print("simulate", report["simulate"], flush=True)
    maps = (info.threshold_on, info.threshold_off)
    wanted = args.cases.split(",")
    cases = {
        "ideal path": (solved_by(rig), events, maps),
        "noise path": (
            solved_by(ev.Rig(threshold_noise=0.01, timestamp_jitter_us=5.0)),
            events,
            maps,
        ),
    }
    if "realistic" in wanted:  # its own capture, with the sensor effects on
        real = ev.Rig(sensor="realistic")
        (ev_r, info_r), cold, warm = timed(
            lambda: ev.simulate(scene, real, sweeps=1, key=jr.key(0), return_info=True),
            0,
        )  # fmt: skip
        report["simulate realistic"] = {"cold_s": cold, "events": len(ev_r)}
        print("simulate realistic", report["simulate realistic"], flush=True)
        cases["realistic path"] = (
            solved_by(real),
            ev_r,
            (info_r.threshold_on, info_r.threshold_off),
        )
    cubes_by_backend = {}
    cases = {k: v for k, v in cases.items() if k.split()[0] in wanted}
    for name, (cal, events_c, maps_c) in cases.items():
        whole_only = args.whole_only or name == "realistic path"

        def rec(cal=cal, backend=args.base_backend, events_c=events_c, maps_c=maps_c):
            return ev.reconstruct(
                events_c, cal, threshold_on_map=maps_c[0], threshold_off_map=maps_c[1],
                backend=backend,
            )  # fmt: skip

        try:
            cube, cold, warm = timed(rec, args.repeats)
        except Exception as err:  # e.g. out of device memory: say so, go on
            report[name] = {"error": repr(err)[:300]}
            print(name, "failed:", repr(err)[:300], flush=True)
            continue
        med = statistics.median(warm)
        metrics = score(cube)
        row = {
            "cold_s": cold,
            "median_s": med,
            "times_s": warm,
            "px_per_s": h * w / med,
            "sam_deg": metrics["sam_deg"],
            "psnr_db": metrics["psnr_db"],
        }
        if not whole_only:
            row.update(device_parts(events, cal, maps, args.repeats))
            row["device_px_per_s"] = h * w / row["device_assemble_solve_s"]
        if args.profile:
            row["profile"] = profiled(rec, args.profile)
        report[name] = row
        print(name, {k: v for k, v in row.items() if "times" not in k and k != "profile"},
              flush=True)  # fmt: skip
        for backend in filter(None, args.backends.split(",")):
            # The whole call with another backend (cuda: the CUDA kernel, which
            # auto picks on a CUDA GPU where numba's CUDA target works).
            try:
                cube_b, cold_b, warm_b = timed(
                    lambda cal=cal, backend=backend: rec(cal, backend), args.repeats
                )  # fmt: skip
            except Exception as err:  # e.g. no CUDA target: say so, go on
                row.setdefault("backends", {})[backend] = {"error": repr(err)[:300]}
                print("  backend", backend, "failed:", repr(err)[:300], flush=True)
                continue
            mb = score(cube_b)
            row.setdefault("backends", {})[backend] = {
                "cold_s": cold_b,
                "median_s": statistics.median(warm_b),
                "times_s": warm_b,
                "px_per_s": h * w / statistics.median(warm_b),
                "sam_deg": mb["sam_deg"],
                "psnr_db": mb["psnr_db"],
                "sam_to_jax_cube_max_deg": float(
                    np.max(ev.metrics.sam_map_deg(cube_b, cube))
                ),
            }
            if args.profile:
                row["backends"][backend]["profile"] = profiled(
                    lambda cal=cal, backend=backend: rec(cal, backend), args.profile
                )  # fmt: skip
            print("  backend", backend, {k: v for k, v in row["backends"][backend]
                  .items() if "times" not in k and k != "profile"}, flush=True)  # fmt: skip
            if name == "ideal path":
                cubes_by_backend[backend] = cube_b
        if name == "ideal path":
            cube32 = cube
            if (
                pipe.DEVICE_GROUPING == "auto" and jax.default_backend() != "cpu"
                and not args.whole_only
            ):  # fmt: skip
                pipe.DEVICE_GROUPING = False  # the whole call with the host's grouping
                cube_h, _, warm_h = timed(rec, args.repeats)
                pipe.DEVICE_GROUPING = "auto"
                row["host_grouping_median_s"] = statistics.median(warm_h)
                row["host_grouping_same_cube"] = bool(np.array_equal(cube_h, cube))
                print("  whole call with host grouping", statistics.median(warm_h),
                      "same cube:", row["host_grouping_same_cube"], flush=True)  # fmt: skip
            for variant in filter(None, args.batch_variants.split(",")):
                c, b = (int(v) for v in variant.split("x"))
                part = device_parts(events, cal, maps, args.repeats, c, b)
                part["device_px_per_s"] = h * w / part["device_assemble_solve_s"]
                row.setdefault("batch_variants", {})[variant] = part
                print("  batch", variant, {k: v for k, v in part.items()
                                           if "times" not in k}, flush=True)  # fmt: skip
    if "ideal path" not in report or args.no_float64:
        return write_json(args.out, report)
    # float32 against a float64 solve of the same events (whole image).
    jax.config.update("jax_enable_x64", True)
    rig64 = solved_by(rig).astype(jnp.float64)
    t = time.perf_counter()
    cube64 = ev.reconstruct(events, rig64, threshold_on_map=maps[0],
                            threshold_off_map=maps[1])  # fmt: skip
    t64 = time.perf_counter() - t
    d = ev.metrics.sam_map_deg(cube32, cube64)
    report["float64_check"] = {
        "seconds_cold": t64,
        "share_within_0.1deg": float(np.mean(d <= 0.1)),
        "median_deg": float(np.median(d)),
        "max_deg": float(np.max(d)),
        "float64_sam_deg": score(cube64)["sam_deg"],
    }
    for backend, cube_b in cubes_by_backend.items():
        d = ev.metrics.sam_map_deg(cube_b, cube64)
        report["float64_check"][backend] = {
            "share_within_0.1deg": float(np.mean(d <= 0.1)),
            "median_deg": float(np.median(d)),
            "max_deg": float(np.max(d)),
        }
    print("float64", report["float64_check"], flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
