"""Which kernel `backend="auto"` takes on a CUDA GPU, by capture size (a check, for
the `device` machine; on a CPU `auto` is the fused backend and this says so).

Prints `_pipeline._use_cuda`'s answer for 921,600 and 13,824 pixel·sweeps, then
reconstructs a 96×144 and a 1280×720 ColorChecker sweep (paper rig, true
thresholds) with `auto`, `cuda` and `jax` (one warm-up call each, then one timed
call), and whether `auto`'s cube is bit for bit the cuda or the jax one.

    XLA_PYTHON_CLIENT_MEM_FRACTION=0.6 PYTHONPATH=. python experiments/check_gpu_auto.py
"""

import time

import jax.random as jr
import numpy as np

import evhsi_jax as ev
from evhsi_jax._base import shard
from evhsi_jax._reconstruct import _pipeline as P

rig = ev.Rig()
spec, cfg = P.solver_spec("auto"), P.ProblemConfig()
print(
    "auto 921600:", P._use_cuda("auto", False, spec, cfg, rig, None, 921600),
    "auto 13824:", P._use_cuda("auto", False, spec, cfg, rig, None, 13824),
)  # fmt: skip
for size in ((96, 144), (720, 1280)):
    sc = ev.load_scene("colorchecker", size)
    e, info = ev.simulate(sc, rig, sweeps=1, key=jr.key(0), return_info=True)
    m = dict(threshold_on_map=info.threshold_on, threshold_off_map=info.threshold_off)
    out = {}
    on_gpu = shard.device_platform() == "gpu"
    backends = ("auto", "cuda", "jax") if on_gpu else ("auto",)
    for b in backends:
        ev.reconstruct(e, rig, backend=b, **m)
        t = time.perf_counter()
        out[b] = ev.reconstruct(e, rig, backend=b, **m)
        dt = time.perf_counter() - t
        sam = ev.evaluate(out[b], sc.truth_cube(rig.grid))["sam_deg"]
        print(size, b, f"warm {dt:.3f} s", "SAM", round(sam, 4))
    if len(out) == 3:
        print(size, "auto==cuda", np.array_equal(out["auto"], out["cuda"]),
              "auto==jax", np.array_equal(out["auto"], out["jax"]))  # fmt: skip
