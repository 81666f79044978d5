"""The GPU path's CUDA kernel (`_reconstruct/_cuda_kernel.py`) run in numba's CUDA
simulator on small random problems (M = 10), against a float64 box-QP solve of the
same rows. The simulator must be chosen before numba's CUDA target is imported, so
the kernel runs in a subprocess. On the GPU, `experiments/bench_gpu_kernel.py`
checks it on a full ColorChecker sweep against float64."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

SCRIPT = r"""
import json, sys
import numpy as np
import pytest
from evhsi_jax._reconstruct import _cuda_kernel as ck
from evhsi_jax._reconstruct._problem import spectral_prior_matrix
from evhsi_jax._reconstruct._fused_jit import _box_qp

assert ck.simulated()
rng = np.random.default_rng(int(sys.argv[1]))
m, k, g, b = 10, 7, 5, 4
ev = np.zeros((b, k, m + 1), np.float32)
drift = np.zeros((b, g, m + 1), np.float32)
ev_n = rng.integers(3, k + 1, b).astype(np.int32)
for arr, n_rows in ((ev, k), (drift, g)):
    for p in range(b):
        for r in range(n_rows):
            lo = rng.integers(0, m - 2)
            hi = min(m, lo + rng.integers(2, 6))
            arr[p, r, lo:hi] = rng.normal(size=hi - lo)
            arr[p, r, m] = rng.normal()
for p in range(b):  # padding rows carry garbage: the kernel must not read them
    ev[p, ev_n[p]:, :] = 1e3
ev_w = rng.uniform(0.2, 1.0, (b, k)).astype(np.float32)
spec_w = rng.uniform(0.01, 0.1, b).astype(np.float32)
spec = spectral_prior_matrix(m, 0.3, "d2")
ridge, tol, iters = 1e-6, 1e-6, 48
out_x = np.zeros((b, m), np.float32)
out_kkt = np.zeros(b, np.float32)
out_steps = np.zeros(b, np.int32)
ck.launch(ev, ev_w, ev_n, drift, spec_w, spec, ridge, tol, iters, out_x, out_kkt,
          out_steps, threads=int(sys.argv[2]), q_global=sys.argv[3] == "1",
          prefetch=sys.argv[4] == "1")
ref = np.zeros((b, m))
for p in range(b):
    r = ev[p, : ev_n[p]].astype(np.float64) * ev_w[p, : ev_n[p], None]
    d = drift[p].astype(np.float64)
    gram = r.T @ r + d.T @ d
    qm = gram[:m, :m] + spec_w[p] * spec
    ridge_p = ridge * ((np.trace(gram[:m, :m]) + spec_w[p] * np.trace(spec)) / m + 1e-30)
    qm += ridge_p * np.eye(m)
    qv = gram[:m, m].copy()
    x = np.zeros(m)
    st = _box_qp(qm, qv, np.zeros(m, np.int64), np.ones(m, bool), np.zeros((m, m)),
                 np.zeros(m), x, np.zeros(m), np.zeros(m), tol, iters, False)
    assert st >= 0
    ref[p] = x
print(json.dumps({"x": out_x.tolist(), "kkt": out_kkt.tolist(),
                  "steps": out_steps.tolist(), "ref": ref.tolist()}))
"""


@pytest.mark.parametrize(("q_global", "prefetch"), [("0", "1"), ("1", "0")])
def test_kernel_matches_a_float64_box_qp(q_global, prefetch):
    # Four threads per pixel (the GPU runs 32): the loops' strides then wrap around
    # M, and the simulator's barriers cost less (~2 s per pixel). Both places of Q,
    # and the rows read ahead of their pass or in it.
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    res = subprocess.run(
        [sys.executable, "-c", SCRIPT, "0", "4", q_global, prefetch], env=env,
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    x, ref = np.array(out["x"]), np.array(out["ref"])
    steps = np.array(out["steps"])
    assert (steps >= 0).all()
    # Random rows with random constants: most minimisers have negative channels, so
    # the active set runs (and the bound is active in the answer).
    assert steps.sum() > 0 and (ref == 0).any()
    scale = np.abs(ref).max(axis=1, keepdims=True)
    np.testing.assert_allclose(x, ref, atol=1e-3 * scale.max(), rtol=0)
    assert (x >= 0).all()
    assert np.all(np.array(out["kkt"]) < 1e-3)


PIPELINE = r"""
import json, sys
import numpy as np
import jax.random as jr
import evhsi_jax as ev
from evhsi_jax._reconstruct import _cuda_kernel as ck

assert ck.simulated()
kw = {} if sys.argv[1] == "ideal" else {"sensor": "realistic"}
rig = ev.Rig(channels=16, **kw)
events = ev.simulate(ev.load_scene("colorchecker", (1, 3)), rig, sweeps=1, key=jr.key(1))
a, info = ev.reconstruct(events, rig, backend="cuda", return_info=True)
b, info_b = ev.reconstruct(events, rig, backend="jax", return_info=True)
out = {"sam": ev.metrics.sam_map_deg(a, b).tolist(), "solved": info.solved.tolist(),
       "kkt": info.kkt.tolist(), "solved_jax": info_b.solved.tolist()}
# One pixel per chunk, grouped and placed by the device (there also the hot pixels'
# fill and the deblurring): the chunks go through the kernels while the next one's
# rows are formed
from evhsi_jax._reconstruct import _pipeline
_pipeline.DEVICE_GROUPING = True
c = ev.reconstruct(events, rig, backend="cuda", chunk_pixels=1, sub_batch=1)
out["sam_chunked"] = ev.metrics.sam_map_deg(c, a).tolist()
print(json.dumps(out))
"""


def _pipeline(case):
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    res = subprocess.run(
        [sys.executable, "-c", PIPELINE, case], env=env, capture_output=True,
        text=True, timeout=900,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_reconstruct_backend_cuda_equals_jax_ideal():
    """`reconstruct(backend="cuda")` (rows by JAX, each pixel's Gram and box QP by
    the kernel, the chunk's padding slots skipped) against the JAX backend, both
    float32: the same cube up to rounding (16 channels, 3 pixels: the simulator)."""
    out = _pipeline("ideal")
    assert np.all(out["solved"])
    assert np.max(out["sam"]) < 0.05
    assert np.all(np.isfinite(out["kkt"]))
    # Three chunks of one pixel each: every answer in its own pixel (the kernel's
    # arithmetic is the same per pixel, so only the places could differ)
    assert np.max(out["sam_chunked"]) < 1e-4


@pytest.mark.slow
def test_reconstruct_backend_cuda_equals_jax_realistic():
    """The same with the realistic preset: the photoreceptor pass (rows relinearised
    at the kernel's answer, by the kernel of `_cuda_lowpass`) and the robust
    reweighting (the kernel's row weights); with one pixel per chunk, the chunks'
    pipeline of the noise path and the device's fill and deblurring.
    Its hot pixels (here the third: its events are dropped, its spectrum filled in)
    are not solved by either backend."""
    out = _pipeline("realistic")
    assert out["solved"] == out["solved_jax"]
    solved = np.array(out["solved"])
    assert solved.sum() >= 2
    assert np.all(np.isfinite(np.array(out["kkt"])[solved]))
    assert np.max(out["sam"]) < 0.05
    assert np.max(out["sam_chunked"]) < 1e-4


PASSES = r"""
import json, sys
import jax
import numpy as np
import jax.random as jr
import evhsi_jax as ev
from evhsi_jax._reconstruct import _cuda_kernel as ck, _pipeline
from evhsi_jax._reconstruct._problem import ProblemConfig

assert ck.simulated()
keep, takes = _pipeline._keep_moved, []

def spy(cfg, more, old, new):  # the CUDA path's passes (eager; JAX's are traced)
    if not isinstance(more, jax.core.Tracer):
        takes.append(int(np.sum(np.asarray(more))))
    return keep(cfg, more, old, new)

_pipeline._keep_moved = spy
solve_rows, solved_n = ck.solve_rows, []

def solve_spy(rows, n, *args, **kw):  # how many pixels each solve is given
    solved_n.append(int(np.sum(np.asarray(n) > 0)))
    return solve_rows(rows, n, *args, **kw)

ck.solve_rows = solve_spy
rig = ev.Rig(channels=16, sensor="realistic")
events = ev.simulate(ev.load_scene("colorchecker", (1, 3)), rig, sweeps=1, key=jr.key(1))
cfg = ProblemConfig(lowpass_tol=float(sys.argv[1]))
a, info = ev.reconstruct(events, rig, backend="cuda", config=cfg, return_info=True)
b = ev.reconstruct(events, rig, backend="jax", config=cfg)
print(json.dumps({"sam": ev.metrics.sam_map_deg(a, b).tolist(), "takes": takes,
                  "solved": int(np.sum(info.solved)), "solved_n": solved_n}))
"""


@pytest.mark.slow
def test_cuda_second_photoreceptor_pass_skips_settled_pixels():
    """After the first photoreceptor pass only the pixels it moved by more than
    `lowpass_tol` take another; on the CUDA path the others are padding slots to
    the rows' and the solve's kernels, and keep their answers. With a tolerance
    at which one of the chunk's pixels goes on and another stops, the cube is
    still the JAX backend's (which computes every pixel's pass and keeps the moved
    ones' answers)."""
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    res = subprocess.run(
        [sys.executable, "-c", PASSES, "0.05"], env=env, capture_output=True,
        text=True, timeout=900,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    takes, solved_n = out["takes"], out["solved_n"]
    assert len(takes) >= 2 and 0 < takes[1] < out["solved"]  # a mixed second pass
    # solves: the first answer, pass 1 (every pixel), pass 2 (the moved ones only)
    assert solved_n[0] == solved_n[1] == out["solved"]
    assert solved_n[2] == takes[1]
    assert np.max(out["sam"]) < 0.05


def test_kernel_variant_strings():
    """The benchmarks' `--variants` (`PLACE:REGS[:pf|nopf]`) as keyword arguments of
    `solve_rows`; anything else is refused."""
    from evhsi_jax._reconstruct import _cuda_kernel as ck

    assert ck.variant("global:none") == {
        "q_global": True, "max_registers": None, "prefetch": ck.PREFETCH,
    }  # fmt: skip
    assert ck.variant("shared:64:pf") == {
        "q_global": False, "max_registers": 64, "prefetch": True,
    }  # fmt: skip
    assert ck.variant("shared:none:nopf")["prefetch"] is False
    for bad in ("gpu:none", "shared:many", "shared", "global:none:fast"):
        with pytest.raises(ValueError, match="PLACE:REGS"):
            ck.variant(bad)


AUTO = r"""
import json, warnings
import numpy as np
import jax.random as jr
import evhsi_jax as ev
from evhsi_jax._base import shard
from evhsi_jax._reconstruct import _cuda_kernel as ck, _pipeline

assert ck.simulated()
out = {"check": ck.self_check(16)}
real_launch = ck.launch
ck.launch = lambda *a, **k: None  # answers never written
out["check_unwritten"] = ck.self_check(12)
def fails(*a, **k):
    raise RuntimeError("CUDA_ERROR_NO_BINARY_FOR_GPU\nmore lines")
ck.launch = fails
out["check_raises"] = ck.self_check(13)
ck.launch = real_launch
rig = ev.Rig(channels=16)
spec, cfg = _pipeline.solver_spec("auto"), _pipeline.ProblemConfig()
shard.device_platform = lambda mesh=None: "gpu"  # as on a CUDA GPU
ck.why_not = lambda *a: None
big, small = _pipeline.AUTO_CUDA_MIN_PIXELS, _pipeline.AUTO_CUDA_MIN_PIXELS - 1
out["auto_default"] = _pipeline._use_cuda("auto", False, spec, cfg, rig, None, big)
out["auto_small"] = _pipeline._use_cuda("auto", False, spec, cfg, rig, None, small)
out["cuda_small"] = _pipeline._use_cuda("cuda", False, spec, cfg, rig, None, small)
_pipeline.AUTO_CUDA = True
out["auto_gpu"] = _pipeline._use_cuda("auto", False, spec, cfg, rig, None)
ck.self_check = lambda m: "RuntimeError: no kernel image"  # a broken CUDA target
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    out["auto_broken"] = _pipeline._use_cuda("auto", False, spec, cfg, rig, None)
out["warned"] = [str(w.message) for w in caught]
out["cuda_broken"] = _pipeline._use_cuda("cuda", False, spec, cfg, rig, None)
_pipeline.AUTO_CUDA = False
out["auto_off"] = _pipeline._use_cuda("auto", False, spec, cfg, rig, None)
print(json.dumps(out))
"""


def test_auto_picks_the_kernel_only_after_its_self_check():
    """`backend="auto"` on a CUDA GPU (faked here: the simulator) takes the kernel
    for a call of at least `AUTO_CUDA_MIN_PIXELS` pixel·sweeps once its self-check
    (a tiny problem with a known answer) passes, and leaves it out for a smaller
    call (numba's fixed start would outweigh the gain) or with `AUTO_CUDA` off; a
    failing check gives a warning naming it and JAX, never an error. `"cuda"` asks
    for the kernel without the check, at any size."""
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    res = subprocess.run([sys.executable, "-c", AUTO], env=env, capture_output=True,
                         text=True, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["check"] is None  # the real kernel, in the simulator, passes
    assert out["check_unwritten"].startswith("wrong answers")
    assert out["check_raises"] == "RuntimeError: CUDA_ERROR_NO_BINARY_FOR_GPU"
    assert out["auto_default"] is True
    assert out["auto_small"] is False
    assert out["cuda_small"] is True
    assert out["auto_gpu"] is True
    assert out["auto_broken"] is False
    assert len(out["warned"]) == 1 and "no kernel image" in out["warned"][0]
    assert out["cuda_broken"] is True
    assert out["auto_off"] is False


def test_kernel_cache_falls_back_where_numba_cannot_cache():
    """The kernel asks numba for its on-disk cache only with the default compile
    options, and where numba refuses the cache (no writable folder: RuntimeError)
    it is compiled without it instead of failing."""
    from evhsi_jax._reconstruct._cuda_kernel import _kernel_jit

    calls = []

    def jit(cache=False, **opts):
        calls.append((cache, opts))
        if cache and opts.get("refuse"):
            raise RuntimeError("cannot cache function: no locator available")
        return lambda fn: ("compiled", fn.__name__, cache)

    def kernel():
        pass

    assert _kernel_jit(jit, {}, True)(kernel) == ("compiled", "kernel", True)
    assert _kernel_jit(jit, {"refuse": 1}, True)(kernel) == ("compiled", "kernel", False)
    assert calls[-2:] == [(True, {"refuse": 1}), (False, {"refuse": 1})]
    assert _kernel_jit(jit, {"max_registers": 64}, False)(kernel)[2] is False
    with pytest.raises(ValueError):  # other errors are not swallowed

        def bad(cache=False, **opts):
            raise ValueError("bad option")

        _kernel_jit(bad, {}, True)(kernel)


LOWPASS = r"""
import json
import numpy as np
import jax.numpy as jnp
import jax.random as jr
import evhsi_jax as ev
from evhsi_jax._reconstruct import _pipeline as pl, _cuda_lowpass as cl, _cuda_kernel as ck
from evhsi_jax._reconstruct._pixels import group_pixels

assert ck.simulated()
# A coarse time grid (the simulator walks it in Python): 96 samples per sweep.
rig = ev.Rig(channels=8, sensor="realistic", samples_per_sweep=96)
events = ev.simulate(ev.load_scene("colorchecker", (1, 3)), rig, sweeps=1, key=jr.key(2))
noise = pl.noise_model(rig)
table = pl.channel_table(rig)
h, w = events.height, events.width
screened, _, _ = pl.screen_events(events, rig, 0, noise, 1, None)
bt = group_pixels(screened, t_start_us=0, chunk_pixels=4, min_chunk=1, merge_below=0)[0][0]
pix = np.where(bt.pixel >= 0, bt.pixel, 0)
offs = np.asarray(rig.column_offsets(w), np.float64)
thr_on = np.linspace(0.9, 1.1, h * w) * float(rig.threshold_on)
thr_off = np.linspace(1.1, 0.9, h * w) * float(rig.threshold_off)
# A carried reference: a clock shift that puts pixel 1's first reference 13 ms before
# the recording, in the sweep before where the band lights the pixel (read a period
# later on the grid, as the fused kernel and JAX read it; not the baseline).
d = np.where(np.arange(pix.size) == 1, 13000.0, 0.0)
px = pl._device_pixels(bt.t_us, bt.polarity, bt.mask, pix, bt.column, d, offs, thr_on,
                       thr_off, np.float32)
noise_j = jnp.asarray(noise, jnp.float32)
cfg = pl.ProblemConfig()
rows, n = pl._chunk_rows(rig, table, cfg, px, 1, noise_j)
x0 = jnp.asarray(np.random.default_rng(0).uniform(0.1, 0.9, (pix.size, 8)), jnp.float32)
ref = pl._chunk_rows(rig, table, cfg, px, 1, noise_j, x0)[0].events
par, g_n = cl.lowpass_params(rig, table, noise, 1)
got = cl.lowpass_rows(px, n, rows.log_weight, x0, table.values, par, g_n)
print(json.dumps({"got": np.asarray(got).tolist(), "ref": np.asarray(ref).tolist(),
                  "n": np.asarray(n).tolist()}))
"""


def test_photoreceptor_rows_kernel_matches_jax():
    """The photoreceptor pass's rows by the kernel of `_cuda_lowpass` (one warp walks
    a pixel's time grid; here 4 simulated threads, 96 grid points) against JAX's
    `_lowpass_rows` (`_chunk_rows` with `x0`): per-pixel thresholds, a pixel with a
    shifted clock, padding rows zero. Only rounding may differ (recursion against
    JAX's associative scan)."""
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    res = subprocess.run(
        [sys.executable, "-c", LOWPASS], env=env, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    got, ref, n = np.array(out["got"]), np.array(out["ref"]), np.array(out["n"])
    assert got.shape == ref.shape and (n >= 2).all()
    scale = np.abs(ref).max()
    assert scale > 0.01  # rows that say something
    np.testing.assert_allclose(got, ref, atol=2e-5 * scale, rtol=0)
    for p, k in enumerate(n):
        assert np.all(got[p, k:] == 0.0)
        assert np.all(np.abs(got[p, :k]).max(axis=1) > 0)
