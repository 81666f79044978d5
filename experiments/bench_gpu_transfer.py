"""How a reconstructed cube best comes home from the GPU, and the host's share of
:class:`DeviceLists` (designed for one GPU; runs anywhere, an option that a device
lacks is reported as an error).

A whole 1280×720 `ev.reconstruct` on an H100 spent ~0.25–0.30 s of its ~0.85 s in
bringing the 270 MB cube back (`bench_gpu.py --profile`: JAX's `_value`, then NumPy's
copy). Timed here on a fresh device array of the cube's shape (`--size`, the paper
rig's channels) each time, medians of `--repeats`:

- `np.array`: what `reconstruct` did (JAX's host copy, then a writable copy);
- `np.asarray`: JAX's host copy alone (read-only);
- `pinned`: `device_put` to the `pinned_host` memory kind, then `np.asarray` of it
  (and `np.array`: writable);
- `numba`: numba's `copy_to_host` into a host array that exists already and whose
  pages were touched (`numba_fresh`: into a new `np.empty`);
- `touch`: making a fresh host array of the cube's size writable page by page
  (`np.empty` + `fill`), on one thread and on 8;
- `lists_serial` / `lists_threaded`: `_pixels._padded_for_device` of `--events`
  random events on one thread and on the usable cores (at most 8).

    python experiments/bench_gpu_transfer.py [--size 720x1280] [--repeats 5]
        [--events 25000000] [--out PATH]

Writes `experiments/results/bench_gpu_transfer.json` (or `--out`).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import statistics
import time
import traceback

import jax
import jax.numpy as jnp
import numpy as np
from _common import matmul_gflops, write_json

import evhsi_jax as ev
from evhsi_jax._reconstruct import _pixels


def times_with_setup(fn, repeats, setup=lambda: None):
    """Median and all times of `fn(setup())`, `setup` untimed."""
    times = []
    for i in range(repeats):
        arg = setup()
        t = time.perf_counter()
        fn(arg)
        times.append(time.perf_counter() - t)
    return {"median_s": statistics.median(times), "times_s": times}


def touch(shape, threads):
    a = np.empty(shape, np.float32)
    if threads == 1:
        a.fill(0.0)
        return a
    flat = a.reshape(-1)
    step = -(-flat.size // threads)
    with concurrent.futures.ThreadPoolExecutor(threads) as pool:
        list(
            pool.map(lambda i: flat[i : i + step].fill(0.0), range(0, flat.size, step))
        )
    return a


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="720x1280")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--events", type=int, default=25_000_000)
    ap.add_argument("--out", default="experiments/results/bench_gpu_transfer.json")
    args = ap.parse_args()
    h, w = ev.forward.parse_size(args.size)
    m = ev.Rig().channels
    dev = jax.devices()[0]
    report = {
        "size": [h, w], "channels": m, "mbytes": h * w * m * 4 / 1e6,
        "backend": jax.default_backend(),
        "device": getattr(dev, "device_kind", str(dev)), "jax": jax.__version__,
        "matmul_gflops_f32": matmul_gflops(1024 if jax.default_backend() == "cpu"
                                           else 8192),
    }  # fmt: skip
    base = jax.random.uniform(jax.random.key(0), (h * w, m), jnp.float32)
    bump = jax.jit(lambda a, i: a + i)
    count = iter(range(10**6))

    def fresh():  # a new device buffer (JAX caches an array's host copy)
        return jax.block_until_ready(bump(base, jnp.float32(next(count))))

    def pinned(x, writable):
        y = jax.device_put(x, x.sharding.with_memory_kind("pinned_host"))
        return np.array(y) if writable else np.asarray(y)

    def numba_into(x, out):
        from numba import cuda

        cuda.as_cuda_array(x).copy_to_host(out)
        return out

    held = {}

    def prefaulted():
        x = fresh()
        held.setdefault("out", touch((h * w, m), 8))
        return x

    cases = {
        "np.array": (np.array, fresh),
        "np.asarray": (np.asarray, fresh),
        "pinned": (lambda x: pinned(x, False), fresh),
        "pinned_writable": (lambda x: pinned(x, True), fresh),
        "numba": (lambda x: numba_into(x, held["out"]), prefaulted),
        "numba_fresh": (
            lambda x: numba_into(x, np.empty((h * w, m), np.float32)),
            fresh,
        ),  # fmt: skip
        "touch_1": (lambda _: touch((h * w, m), 1), lambda: None),
        "touch_8": (lambda _: touch((h * w, m), 8), lambda: None),
    }
    for name, (fn, setup) in cases.items():
        try:
            if setup is fresh or setup is prefaulted:  # the answer is the array's
                x = setup()
                got = np.asarray(fn(x))
                want = np.asarray(jax.device_get(x))
                report.setdefault("same_values", {})[name] = bool(
                    np.array_equal(got, want)
                )  # fmt: skip
            report[name] = times_with_setup(fn, args.repeats, setup)
        except Exception as err:  # e.g. no numba CUDA target, no pinned memory
            report[name] = {"error": "".join(
                traceback.format_exception_only(type(err), err)).strip()[:300]}  # fmt: skip
        print(name, report[name], flush=True)

    rng = np.random.default_rng(0)
    n = args.events
    events = ev.io.EventStream(
        x=rng.integers(0, w, n).astype(np.uint16), y=rng.integers(0, h, n).astype(np.uint16),
        p=rng.integers(0, 2, n).astype(np.uint8),
        t_us=np.sort(rng.integers(0, 1_000_000, n)).astype(np.int64), width=w, height=h,
    )  # fmt: skip
    default = _pixels.THREADED_LISTS_MIN
    for name, least in (("lists_serial", 1 << 62), ("lists_threaded", default)):
        _pixels.THREADED_LISTS_MIN = least
        report[name] = times_with_setup(
            lambda _: _pixels._padded_for_device(events, 0), args.repeats
        )  # fmt: skip
        print(name, report[name], flush=True)
    _pixels.THREADED_LISTS_MIN = default
    write_json(args.out, report)


if __name__ == "__main__":
    main()
