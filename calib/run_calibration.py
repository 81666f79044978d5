"""Calibrate a rig: gray-chart capture → calibration file → report.

Usage: `.venv/bin/python calib/run_calibration.py [--config calib/config.json]
[--out calib/out] [--size HxW]`

With `"capture": null` in the config the gray-chart capture is *simulated* from
`true_rig` (thresholds, β, c differ from the initial rig; the column offsets get a
smooth wiggle of `column_offset_wiggle_us`; the camera response gets a linear tilt the
initial rig does not know), and the report compares every fitted value with the truth.
With a recorded capture (`.raw`/`.npz` of the gray chart filling the sensor) the same
steps run and the report shows the fit and its residuals.

Steps and outputs (under --out):
1. `gray_chart.npz` — the capture (simulated case);
2. `calibration.json` + `calibration_thresholds.npz` — the joint fit (`evhsi_jax.calibrate`);
3. `white_reference`: a white patch of known spectrum is captured and reconstructed with
   the calibrated rig; per-channel factors correct D(λ) → `calibration_corrected.json`;
4. end to end: the `evaluate_scene` (ColorChecker) captured by the same sensor and
   reconstructed with the true rig, the calibrated rig and the initial rig;
5. `report.json`, `report.png` (residuals, fit vs data, τx error, spectra).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax.random as jr
import numpy as np

import evhsi_jax as ev

HERE = Path(__file__).parent


def true_rig(cfg: dict, width: int, base: Path) -> ev.Rig:
    data = json.loads((base / cfg["true_rig"]).read_text())
    data.pop("comment", None)
    x = np.arange(width)
    offs = np.asarray(
        ev.Rig(
            **{k: v for k, v in data.items() if k == "sweep_rate_hz"}
        ).column_offsets(width),
        np.float64,
    )
    offs = offs + cfg.get("column_offset_wiggle_us", 0.0) * np.sin(
        2 * np.pi * x / max(width / 2, 8)
    )
    data["column_offsets_us"] = offs.tolist()
    tilt = cfg.get("true_camera_tilt", 0.0)
    if tilt:
        wl = np.arange(400.5, 760, 1.0)
        d = ev.forward.default_camera_response(wl) * (1 + tilt * (wl - 580.0) / 180.0)
        data["camera_response"] = {"wavelengths_nm": wl.tolist(), "values": d.tolist()}
    return ev.Rig.from_dict(data)


FITTED = ("threshold_on", "threshold_off", "beta_nm_per_rad", "baseline_rel")


def true_values(truth: ev.Rig, sim) -> dict:
    """The true value of each globally fitted parameter; a threshold's is the
    simulated sensor's population mean (`sim`: the simulation's info)."""
    return {
        "threshold_on": float(np.mean(sim.threshold_on)),
        "threshold_off": float(np.mean(sim.threshold_off)),
        "beta_nm_per_rad": float(truth.beta_nm_per_rad),
        "baseline_rel": float(truth.baseline_rel),
    }


def rms(a, b) -> float:
    """Root mean square of a − b (float64)."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    return float(np.sqrt(np.mean(d**2)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(HERE / "config.json"))
    ap.add_argument("--out", default=str(HERE / "out"))
    ap.add_argument("--size", default=None, help="override the config's HxW")
    args = ap.parse_args()
    cfg_path = Path(args.config)
    cfg = json.loads(cfg_path.read_text())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    init = (
        ev.Rig.load(cfg_path.parent / cfg["init_rig"])
        if cfg.get("init_rig")
        else ev.Rig()
    )
    report: dict = {"config": cfg}
    simulated = cfg.get("capture") is None
    chart_name = cfg.get("chart", "gray-chart")
    if simulated:
        h, w = ev.forward.parse_size(args.size or cfg["size"])
        truth = true_rig(cfg, w, cfg_path.parent)
        key = jr.key(cfg.get("seed", 0))  # one key = one sensor (its threshold map)
        chart = ev.load_scene(chart_name, (h, w))
        t0 = time.perf_counter()
        events, sim = ev.simulate(
            chart,
            truth,
            sweeps=cfg.get("sweeps", 2),
            key=key,
            return_info=True,
            progress=True,
        )
        report["simulate_s"] = time.perf_counter() - t0
        ev.write_events(out / "gray_chart.npz", events)
    else:
        events = ev.read_events(cfg_path.parent / cfg["capture"])
        h, w = events.height, events.width
        chart = ev.load_scene(chart_name, (h, w))
    print(f"capture: {len(events):,} events, {h}x{w}")

    res = ev.calibrate(events, chart, init, rows_per_label=cfg.get("rows_per_patch", 4))
    ev.save_calibration(
        out / "calibration.json", res, comment="calib/run_calibration.py"
    )
    rig = res.rig
    report["fit"] = {
        "seconds": res.seconds,
        "steps": res.steps,
        "events_used": res.events_used,
        "rms_residual_log": res.rms_residual,
        "rms_residual_initial_log": res.rms_residual_initial,
    }
    rows = []
    true_vals = true_values(truth, sim) if simulated else {}
    for k in FITTED:
        row = {
            "parameter": k,
            "initial": float(getattr(init, k)),
            "fitted": float(getattr(rig, k)),
        }
        if simulated:
            tv = true_vals[k]
            row.update(true=tv, error_pct=100 * (row["fitted"] / tv - 1))
        rows.append(row)
    report["parameters"] = rows
    tau_fit = np.asarray(rig.column_offsets_us, np.float64)
    tau_true = np.asarray(truth.column_offsets(w), np.float64) if simulated else None
    if simulated:
        report["column_offsets_rms_error_us"] = rms(tau_fit, tau_true)
        report["threshold_map_rms_error"] = {
            "on": rms(res.threshold_on_map, sim.threshold_on),
            "off": rms(res.threshold_off_map, sim.threshold_off),
            "true_spread": float(np.std(sim.threshold_on)),
        }
    print(f"\n| parameter | initial | fitted |{' true | error |' if simulated else ''}")
    print(f"|---|---:|---:|{'---:|---:|' if simulated else ''}")
    for r in rows:
        tail = f" {r['true']:.5g} | {r['error_pct']:+.3f} % |" if simulated else ""
        print(f"| {r['parameter']} | {r['initial']:.5g} | {r['fitted']:.5g} |{tail}")
    if simulated:
        print(
            f"| column offsets | RMS error {report['column_offsets_rms_error_us']:.2f} µs |"
        )
        m = report["threshold_map_rms_error"]
        print(
            f"| per-pixel thresholds | RMS error ON {m['on']:.5f}, OFF {m['off']:.5f} "
            f"(true spread {m['true_spread']:.4f}) |"
        )
    print(
        f"fit: {res.steps} LM steps, {res.seconds:.1f} s, rms residual "
        f"{res.rms_residual:.2e} thresholds (start {res.rms_residual_initial:.2e})"
    )

    maps = dict(
        threshold_on_map=res.threshold_on_map, threshold_off_map=res.threshold_off_map
    )
    corrected = rig
    if simulated and cfg.get("white_reference"):
        names, wl, pal = _white()
        white = ev.Scene(pal[None], wl, np.zeros((h, w), int), ("white",))
        ev_white = ev.simulate(white, truth, sweeps=1, key=key)
        cube_white = ev.reconstruct(ev_white, rig, **maps)
        factors = ev.calibration.spectral_correction(cube_white, white.truth_cube(rig.grid)[0, 0])
        corrected = ev.calibration.apply_spectral_correction(rig, factors)
        cfg_c = corrected.to_dict()
        cfg_c["threshold_map"] = "calibration_thresholds.npz"
        cfg_c["comment"] = "calibration.json with D(λ) corrected from a white reference"
        (out / "calibration_corrected.json").write_text(
            json.dumps(cfg_c, indent=2) + "\n"
        )
        report["spectral_correction"] = {
            "factors_min": float(factors.min()),
            "factors_max": float(factors.max()),
        }

    if simulated and cfg.get("evaluate_scene"):
        scene = ev.load_scene(cfg["evaluate_scene"], (h, w))
        ev_scene, sim2 = ev.simulate(scene, truth, sweeps=1, key=key, return_info=True)
        gt = scene.truth_cube(truth.grid)
        variants = {
            "true rig + true per-pixel thresholds": (
                truth,
                dict(
                    threshold_on_map=sim2.threshold_on,
                    threshold_off_map=sim2.threshold_off,
                ),
            ),
            "calibrated rig + maps": (rig, maps),
            "calibrated + white-reference gains + maps": (corrected, maps),
            "initial rig (nominal thresholds)": (init, {}),
        }
        e2e = {}
        for name, (r, kw) in variants.items():
            cube = ev.reconstruct(ev_scene, r, **kw)
            e2e[name] = ev.evaluate(cube, gt)
        report["end_to_end"] = e2e
        print(
            f"\n| {cfg['evaluate_scene']} reconstructed with | SAM° | PSNR dB |\n|---|---:|---:|"
        )
        for name, m in e2e.items():
            print(f"| {name} | {m['sam_deg']:.2f} | {m['psnr_db']:.2f} |")

    _plot(
        out / "report.png",
        events,
        chart,
        rig,
        res,
        tau_fit,
        tau_true,
    )
    (out / "report.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"\nwrote {out}/calibration.json, report.json, report.png")


def _white():
    scene = ev.load_scene("colorchecker", (4, 6))
    i = list(scene.names).index("white 9.5 (.05 D)")
    return scene.names, scene.wavelengths_nm, scene.palette[i]


def _plot(path, events, chart, rig, res, tau_fit, tau_true):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = ev.calibration.chart_data(events, chart, rig, rows_per_label=2)
    resid = np.asarray(ev.calibration.chart_residuals(rig, data))
    steps = np.asarray(ev.calibration.chart_log_steps(rig, data))
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    axes[0].hist(resid[data.mask], bins=80)
    axes[0].set_title("event residuals (thresholds), global thresholds")
    for s in range(data.spectra.shape[0]):
        sel = (data.spectrum == s)[:, None] & data.mask
        axes[1].plot(
            data.t_us[sel][:400] % float(rig.period_us), steps[sel][:400], ".", ms=2
        )
    axes[1].axhline(float(rig.threshold_on), color="k", lw=0.5)
    axes[1].axhline(-float(rig.threshold_off), color="k", lw=0.5)
    axes[1].set_title("model log step at observed events (per patch)")
    axes[1].set_xlabel("time in sweep (µs)")
    if tau_true is not None:
        axes[2].plot(tau_fit - tau_true)
        axes[2].set_title("column offset error (µs)")
    else:
        axes[2].plot(tau_fit)
        axes[2].set_title("fitted column offsets (µs)")
    axes[2].set_xlabel("column")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
