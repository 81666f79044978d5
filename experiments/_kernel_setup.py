"""The fused kernel's inputs for a kernel-level study (`bench_kernel_ab.py`,
`profile_kernel.py`): uses the package's private modules, unlike `_common.py`."""

from __future__ import annotations

from types import SimpleNamespace

import jax.random as jr
import numpy as np

import evhsi_jax as ev
from evhsi_jax._reconstruct import _fused
from evhsi_jax._reconstruct import _pipeline as pipe
from evhsi_jax._reconstruct._pixels import pixel_lists
from evhsi_jax._reconstruct._problem import ProblemConfig


def fused_inputs(sensor: str, size: str) -> SimpleNamespace:
    """One sweep of the ColorChecker at `size`, paper rig with the `sensor` preset
    (`noise`: threshold noise 0.01 and 5 µs jitter only), the true rig as the
    calibration and the true per-pixel thresholds; the events screened and listed per
    pixel. Returns `prob`, `sel` and `args` (the arguments of
    `_fused.solve_fused` after them), and `table`: the channel table as it comes from
    the rig, before `FusedProblem` trims it (float64)."""
    h, w = ev.forward.parse_size(size)
    if sensor == "noise":  # threshold noise and jitter: weights, reweighting
        rig = ev.Rig(threshold_noise=0.01, timestamp_jitter_us=5.0)
    else:
        rig = ev.Rig(sensor=sensor)
    scene = ev.load_scene("colorchecker", (h, w))
    events, info = ev.simulate(scene, rig, sweeps=1, key=jr.key(0), return_info=True)
    t0 = int(events.trigger_t_us[0]) if events.trigger_t_us.size else 0
    noise = pipe.noise_model(rig)
    kept, _, _ = pipe.screen_events(events, rig, t0, noise, 1, None)
    counts, starts, t_rel, sgn = pixel_lists(kept, t0)
    offs = np.asarray(rig.column_offsets(w), np.float64)
    table = pipe.channel_table(rig)
    prob = _fused.FusedProblem(
        rig, table, ProblemConfig(), pipe.solver_spec("auto"), w, offs, 1, noise,
    )  # fmt: skip
    args = (
        starts, counts, t_rel, sgn, np.zeros(h * w),
        np.asarray(info.threshold_on, np.float64).ravel(),
        np.asarray(info.threshold_off, np.float64).ravel(),
    )  # fmt: skip
    return SimpleNamespace(
        prob=prob, sel=np.flatnonzero(counts), args=args, size=(h, w),
        table=np.asarray(table.values, np.float64),
    )  # fmt: skip


def run_lane_solves(mod, setup: SimpleNamespace, sel: np.ndarray, on_solve):
    """Solve the pixels `sel` of `setup` (:func:`fused_inputs`) through the kernel
    module `mod`'s Python source around its compiled inner functions, calling
    `on_solve(ql, qvl, fu)` with each four-lane system (Q, q, union envelope) just
    before `_solve_lanes` solves it; slow, so for a sample of pixels. Returns the
    kernel's `(x, kkt, steps)`; the module's functions are put back after."""
    solve, group, assemble = mod._solve_lanes, mod._solve_group, mod._lane_assemble

    def spy(ql, qvl, fu, *rest):
        on_solve(ql, qvl, fu)
        return solve(ql, qvl, fu, *rest)

    mod._solve_lanes, mod._solve_group = spy, group.py_func
    mod._lane_assemble = assemble.py_func
    try:
        m = setup.prob.channels
        args = _fused.kernel_inputs(setup.prob, *setup.args)
        x, kkt = np.empty((sel.size, m)), np.empty(sel.size)
        steps = np.empty(sel.size, np.int64)
        mod.solve_pixels.py_func(sel, *args, x, kkt, steps, np.empty((sel.size, 3)))
    finally:
        mod._solve_lanes, mod._solve_group, mod._lane_assemble = solve, group, assemble
    return x, kkt, steps
