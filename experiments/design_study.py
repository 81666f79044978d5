"""Optical design by gradients: optimise, validate on held-out spectra, trade-offs.

Setup. The design is (FWHM, β, λ0, c, C, sweep rate); 72 channels, refractory 50 µs,
D(λ) and E(λ) stay the paper rig's. Hardware limits: 80 Mev/s over a 1280×720 sensor,
30 sweeps/s mechanical limit, c ≥ 1 % of a white pixel's peak, the sweep must cover the
channels; the application asks for at least 3 sweeps/s (the lower end of the box).

1. Optimise the differentiable design loss (expected log-MSE of the per-pixel QP
   reconstruction over the sensor's threshold mismatch, on `tcs` test-colour samples
   at three brightness gains) with Adam from the paper's default design.
2. Validate the default and the optimum with the exact simulator and the standard
   reconstruction (`evhsi_jax.simulate` + `evhsi_jax.reconstruct`, per-pixel
   thresholds C·(1 + 0.067 z) known to the reconstruction) on HELD-OUT reflectances:
   the ColorChecker (disjoint from the training set).
3. Trade-off curves on the held-out chart from the exact pipeline (error vs FWHM, c,
   C and event rate) through the optimum, the optimum and the default marked.
4. Gradient check: the design gradient's predicted change of the training error vs the
   exact pipeline's central finite differences on the same training spectra.

Machine: whatever runs it (printed into the JSON); the numbers in DESIGN_STUDY.md are
from a 2-core CPU VM shared with other jobs.

    nice -n 10 .venv/bin/python experiments/design_study.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

import evhsi_jax as ev

sys.path.insert(0, str(Path(__file__).parent))
from _common import OUT, machine, pyplot, save  # noqa: E402

# Run each computation on the calling thread: with asynchronous dispatch this study hung
# (every XLA worker idle, Python waiting on a result) three times on a busy 2-core VM.
jax.config.update("jax_cpu_enable_async_dispatch", False)

SPACE = ev.DesignSpace(sweep_rate_hz=(3.0, 60.0), beta_nm_per_rad=(160.0, 400.0))
LIMITS = ev.DesignLimits()
SPREAD = 0.067  # threshold mismatch relative to C: the paper's N(0.15, 0.01)
NAMES = ("fwhm_nm", "beta_nm_per_rad", "baseline_rel", "threshold", "sweep_rate_hz")
# Central finite-difference factors of the exact pipeline (multiplicative).
FD_FACTOR = {
    "fwhm_nm": 1.15,
    "beta_nm_per_rad": 1.1,
    "baseline_rel": 1.25,
    "threshold": 1.1,
    "sweep_rate_hz": 1.25,
}


def replace(p: ev.DesignParams, **kw) -> ev.DesignParams:
    d = p.as_dict()
    d.update({k: float(v) for k, v in kw.items()})
    return ev.DesignParams.from_dict(d)


def fit_geometry(p: ev.DesignParams, fwhm_nm: float | None = None) -> ev.DesignParams:
    """`p` (with `fwhm_nm` if given) with λ0 lowered and β raised just enough for the
    sweep to cover the channels ± 2 FWHM at every column (else `simulate` refuses);
    λ0 leaves the error unchanged (it only shifts event times), β hardly changes it."""
    f = float(p.fwhm_nm) if fwhm_nm is None else float(fwhm_nm)
    grid = ev.Rig().grid
    start = min(float(p.sweep_start_nm), grid.start_nm - 2.0 * f - 0.5)
    swept = (1.0 - LIMITS.column_spread) * np.pi
    beta = max(float(p.beta_nm_per_rad), (grid.stop_nm + 2.0 * f + 0.5 - start) / swept)
    return replace(p, fwhm_nm=f, sweep_start_nm=start, beta_nm_per_rad=beta)


def held_out(p, cfg, seeds=None):
    """Exact simulate + reconstruct on the ColorChecker, averaged over seeds."""
    rows = [
        ev.evaluate_design(
            p,
            "colorchecker",
            base_rig=ev.Rig(threshold_sigma=0.0),
            limits=LIMITS,
            size=cfg["held_size"],
            seed=s,
            threshold_spread=SPREAD,
        )
        for s in (seeds or cfg["seeds"])
    ]
    out = {
        k: float(np.mean([r[k] for r in rows]))
        for k in ("sam_deg", "psnr_db", "rms", "ssim", "events_per_pixel")
    }
    out["event_rate_ev_s"] = float(np.mean([r["event_rate_ev_s"] for r in rows]))
    out["feasible"] = all(r["feasible"] for r in rows)
    out["constraints"] = rows[0]["constraints"]
    out["params"] = p.as_dict()
    return out


def training_exact(p, cfg, seed=0):
    """Exact-pipeline log-MSE on the training spectra (the design loss's own set)."""
    scene = ev.training_scene(
        gains=cfg["gains"], repeats=cfg["train_rows"], limit=cfg["spectra"]
    )
    r = ev.evaluate_design(
        p,
        scene,
        base_rig=ev.Rig(threshold_sigma=0.0),
        limits=LIMITS,
        size=None,
        seed=seed,
        threshold_spread=SPREAD,
    )
    return float(np.log(r["rms"] ** 2)), r


@functools.cache
def _vg(score: bool):
    @eqx.filter_jit
    def vg(problem, u, key):
        return ev.design_value_and_grad(problem, u, key=key, score=score)

    return vg


def soft_gradient(problem, p, n_keys, score=True):
    """d log-MSE / d(physical parameter) from the design gradient (error part only),
    averaged over `n_keys` jitter draws."""
    u = problem.space.to_unconstrained(p)
    vg = _vg(score)
    gs = [vg(problem, u, jr.key(100 + i))[2]["grad_log_mse"] for i in range(n_keys)]
    g_u = jax.tree.map(lambda *v: jnp.mean(jnp.stack(v)), *gs)
    out = {}
    for name in NAMES:

        def phys(v, name=name):
            return getattr(
                problem.space.from_unconstrained(
                    eqx.tree_at(lambda q: getattr(q, name), u, v)
                ),
                name,
            )

        dp_du = jax.grad(phys)(getattr(u, name))
        out[name] = float(getattr(g_u, name) / dp_du)
    return out


def gradient_check(problem, p, cfg, label):
    """Predicted Δ log-MSE (soft gradient × step) vs the exact pipeline's difference."""
    g_score = soft_gradient(problem, p, cfg["grad_keys"], score=True)
    g_path = soft_gradient(problem, p, cfg["grad_keys"], score=False)
    rows = {}
    for name in NAMES:
        f = FD_FACTOR[name]
        v = float(getattr(p, name))
        lo, hi = v / f, v * f
        q = fit_geometry(p, hi) if name == "fwhm_nm" else p  # same λ0, β at ± steps
        e_hi, _ = training_exact(replace(q, **{name: hi}), cfg)
        e_lo, _ = training_exact(replace(q, **{name: lo}), cfg)
        rows[name] = {
            "step": [lo, hi],
            "exact_delta": e_hi - e_lo,
            "predicted_delta": g_score[name] * (hi - lo),
            "pathwise_delta": g_path[name] * (hi - lo),
        }
        r = rows[name]
        agree = np.sign(r["exact_delta"]) == np.sign(r["predicted_delta"])
        print(
            f"[grad check @ {label}] {name:16s} exact Δ {r['exact_delta']:+.4f}  "
            f"design-gradient Δ {r['predicted_delta']:+.4f}  "
            f"pathwise Δ {r['pathwise_delta']:+.4f}  sign {'ok' if agree else 'DIFFERS'}",
            flush=True,
        )
    return rows


def curves(p_opt, p_def, cfg):
    """Exact-pipeline trade-offs through the optimum (and the default's C sweep)."""
    grids = {
        "fwhm_nm": cfg["fwhm_grid"],
        "baseline_rel": cfg["c_grid"],
        "threshold": cfg["C_grid"],
    }
    out = {}
    for name, grid in grids.items():
        vals = sorted(set(grid) | {round(float(getattr(p_opt, name)), 4)})
        out[name] = []
        for v in vals:
            q = replace(p_opt, **{name: v})
            q = fit_geometry(q) if name == "fwhm_nm" else q
            r = held_out(q, cfg, seeds=cfg["seeds"][:1])
            r["value"] = v
            out[name].append(r)
            print(
                f"[curve {name}] {v:8.4f}: PSNR {r['psnr_db']:.2f} dB  "
                f"SAM {r['sam_deg']:.2f}°  {r['event_rate_ev_s'] / 1e6:.1f} Mev/s",
                flush=True,
            )
    # Bandwidth: the C sweep of the default optics at the optimum's sweep rate.
    base = replace(p_def, sweep_rate_hz=float(p_opt.sweep_rate_hz))
    out["bandwidth_default_optics"] = []
    for v in cfg["C_grid"]:
        r = held_out(replace(base, threshold=v), cfg, seeds=cfg["seeds"][:1])
        r["value"] = v
        out["bandwidth_default_optics"].append(r)
        print(
            f"[curve C, default optics] {v:.3f}: PSNR {r['psnr_db']:.2f} dB  "
            f"{r['event_rate_ev_s'] / 1e6:.1f} Mev/s",
            flush=True,
        )
    return out


def figure(result, traj, cur, checks):
    plt = pyplot()
    fig, ax = plt.subplots(2, 3, figsize=(15, 8.5))
    a = ax[0, 0]
    steps = [r["step"] for r in traj]
    a.plot(steps, [r["psnr_db"] for r in traj], label="training PSNR (design loss)")
    a.set_xlabel("Adam step")
    a.set_ylabel("PSNR, dB")
    a2 = a.twinx()
    a2.plot(steps, [r["event_rate_ev_s"] / 1e6 for r in traj], "C1", label="event rate")
    a2.axhline(LIMITS.max_event_rate_ev_s / 1e6, color="C1", ls=":", lw=1)
    a2.set_yscale("log")
    a2.set_ylabel("event rate, Mev/s (full sensor)")
    a.set_title("(a) optimiser trajectory")
    a.legend(loc="lower right", fontsize=8)
    opt, dflt = result["optimum"], result["default"]
    labels = {
        "fwhm_nm": ("(b) error vs FWHM", "FWHM, nm"),
        "baseline_rel": ("(c) error vs constant light c", "c (fraction of white peak)"),
        "threshold": ("(d) error vs threshold C", "C, log units"),
    }
    for axi, name in zip((ax[0, 1], ax[0, 2], ax[1, 0]), labels):
        pts = cur[name]
        x = [r["value"] for r in pts]
        y = [r["psnr_db"] for r in pts]
        axi.plot(x, y, "k-", lw=1)
        for r in pts:
            axi.plot(
                r["value"],
                r["psnr_db"],
                "o",
                color="k",
                mfc="k" if r["feasible"] else "w",
            )
        axi.plot(opt["params"][name], opt["psnr_db"], "r*", ms=14, label="optimum")
        axi.plot(dflt["params"][name], dflt["psnr_db"], "bs", ms=8, label="default")
        axi.set_title(labels[name][0])
        axi.set_xlabel(labels[name][1])
        axi.set_ylabel("held-out PSNR, dB (open: infeasible)")
        if name != "fwhm_nm":
            axi.set_xscale("log")
        axi.legend(fontsize=8)
    a = ax[1, 1]
    for key, lab, col in (
        ("threshold", "C sweep, optimum's optics", "r"),
        ("bandwidth_default_optics", "C sweep, default optics", "b"),
    ):
        pts = sorted(cur[key], key=lambda r: r["event_rate_ev_s"])
        a.plot(
            [r["event_rate_ev_s"] / 1e6 for r in pts],
            [r["psnr_db"] for r in pts],
            "o-",
            color=col,
            label=lab,
        )
    a.plot(opt["event_rate_ev_s"] / 1e6, opt["psnr_db"], "r*", ms=14, label="optimum")
    a.plot(dflt["event_rate_ev_s"] / 1e6, dflt["psnr_db"], "bs", ms=8, label="default")
    a.axvline(LIMITS.max_event_rate_ev_s / 1e6, color="k", ls=":", lw=1)
    a.set_xscale("log")
    a.set_xlabel("event rate, Mev/s (1280×720 at the design's sweep rate)")
    a.set_ylabel("held-out PSNR, dB")
    a.set_title("(e) error vs bandwidth")
    a.legend(fontsize=8)
    a = ax[1, 2]
    names = list(NAMES)
    w = 0.38
    for i, (label, rows) in enumerate(checks.items()):
        ex = np.array([rows[n]["exact_delta"] for n in names])
        pr = np.array([rows[n]["predicted_delta"] for n in names])
        xs = np.arange(len(names)) + (i - 0.5) * w
        a.bar(xs, ex, w * 0.5, color=f"C{2 * i}", label=f"exact FD @ {label}")
        a.bar(
            xs + w * 0.5,
            pr,
            w * 0.5,
            color=f"C{2 * i + 1}",
            label=f"gradient @ {label}",
        )
    a.axhline(0, color="k", lw=0.5)
    a.set_xticks(np.arange(len(names)), [n.split("_")[0] for n in names])
    a.set_ylabel("Δ log-MSE over the central step")
    a.set_title("(f) design gradient vs exact finite differences")
    a.legend(fontsize=7)
    fig.tight_layout()
    return fig


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--steps", type=int, default=None, help="Adam steps")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    if args.quick:
        cfg = dict(
            spectra=6,
            gains=(1.0,),
            steps=3,
            lr=0.1,
            average=2,
            held_size=(8, 12),
            seeds=(0,),
            train_rows=1,
            grad_keys=1,
            fwhm_grid=(12.0, 25.0),
            c_grid=(0.01, 0.05),
            C_grid=(0.1, 0.2),
        )
        name = "design_study_quick"
    else:
        cfg = dict(
            spectra=12,
            gains=(1.0, 0.64),
            steps=40,
            lr=0.1,
            average=10,
            held_size=(16, 24),
            seeds=(0, 1),
            train_rows=2,
            grad_keys=4,
            fwhm_grid=(8.0, 12.0, 17.5, 25.0, 35.0),
            c_grid=(0.01, 0.02, 0.03, 0.06, 0.12),
            C_grid=(0.08, 0.11, 0.15, 0.2, 0.27, 0.36),
        )
        name = "design_study"
    if args.steps is not None:
        cfg["steps"] = args.steps
    problem = ev.design_problem(
        spectra_limit=cfg["spectra"], gains=cfg["gains"], space=SPACE, limits=LIMITS
    )
    p_def = ev.DesignParams.from_rig(ev.Rig())
    print(
        f"training pixels {problem.truth.shape[0]}, time grid "
        f"{problem.structure.n_steps} steps; start {p_def.as_dict()}",
        flush=True,
    )

    # 1. optimise
    res = ev.optimise_design(
        problem,
        p_def,
        steps=cfg["steps"],
        learning_rate=cfg["lr"],
        average=cfg["average"],
        print_every=5,
        key=jr.key(0),
    )
    p_opt = res.params
    OUT.mkdir(exist_ok=True)
    ev.save_trajectory(OUT / f"{name}_trajectory.json", res, config=cfg)
    t_opt = res.seconds
    print(f"optimum {p_opt.as_dict()} after {t_opt:.0f} s", flush=True)

    # 2. held-out validation
    t0 = time.perf_counter()
    p_def_req = replace(p_def, sweep_rate_hz=SPACE.sweep_rate_hz[0])
    val = {
        "default": held_out(p_def, cfg),
        "default_at_required_rate": held_out(p_def_req, cfg),
        "optimum": held_out(p_opt, cfg),
    }
    for k, r in val.items():
        print(
            f"[held-out] {k:26s} SAM {r['sam_deg']:.2f}°  PSNR {r['psnr_db']:.2f} dB  "
            f"events/px {r['events_per_pixel']:.1f}  "
            f"{r['event_rate_ev_s'] / 1e6:.1f} Mev/s  feasible {r['feasible']}",
            flush=True,
        )
    t_val = time.perf_counter() - t0

    # 3. gradient directions vs the exact pipeline
    t0 = time.perf_counter()
    checks = {
        "default": gradient_check(problem, p_def_req, cfg, "default@3Hz"),
        "optimum": gradient_check(problem, p_opt, cfg, "optimum"),
    }
    t_grad = time.perf_counter() - t0

    # 4. trade-off curves
    t0 = time.perf_counter()
    cur = curves(p_opt, p_def, cfg)
    t_cur = time.perf_counter() - t0

    wall = time.perf_counter() - t_start
    payload = {
        "config": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
        "space": {k: list(getattr(SPACE, k)) for k in SPACE.__dataclass_fields__},
        "limits": {k: getattr(LIMITS, k) for k in LIMITS.__dataclass_fields__},
        "threshold_spread": SPREAD,
        "held_out": val,
        "gradient_check": checks,
        "curves": cur,
        "trajectory_file": f"{name}_trajectory.json",
        "trajectory_last": res.trajectory[-1],
        "seconds": {
            "optimise": t_opt,
            "validate": t_val,
            "gradient_check": t_grad,
            "curves": t_cur,
            "total": wall,
        },
        "machine_detail": machine(),
    }
    fig = figure(
        {"optimum": val["optimum"], "default": val["default"]},
        res.trajectory,
        cur,
        checks,
    )
    save(name, payload, fig)
    print(f"total wall time {wall:.0f} s", flush=True)


if __name__ == "__main__":
    main()
