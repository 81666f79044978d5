"""`make demo`: the main job on the built-in default scene.

One simulated sensor (the paper's rig: per-pixel threshold mismatch, refractory period)
first captures the gray chart, from which the rig is calibrated (thresholds, β, c, column
offsets, per-pixel threshold maps), then captures the ColorChecker, which is
reconstructed with the nominal rig, with the calibration, and (as a reference) with the
simulator's own per-pixel thresholds. Prints the event statistics, bandwidth and
metrics; writes the events, truth, calibration, cubes and an sRGB comparison image.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax.random as jr
import numpy as np

from ._base import evaluate
from ._calibrate import calibrate, save_calibration
from ._io import cube_to_srgb, evt3_bytes, save_cube, write_comparison_png, write_events
from ._model import Rig, load_scene, parse_size
from ._reconstruct import reconstruct
from ._simulate import simulate

__all__ = ["run_demo"]


def run_demo(out: Path, size: str = "96x144", quiet: bool = False) -> dict:
    """Run the demo, writing into `out`; returns the metrics rows."""
    out.mkdir(parents=True, exist_ok=True)
    rig = Rig()
    scene = load_scene("colorchecker", parse_size(size))
    h, w = scene.height, scene.width
    print(
        f"evhsi demo: ColorChecker {h}x{w}, paper rig (72 ch 400-760 nm, FWHM "
        f"{float(rig.fwhm_nm):g} nm, C = {float(rig.threshold_on):g} ± "
        f"{rig.threshold_sigma:g}, refractory {float(rig.refractory_us):g} µs, "
        f"{float(rig.sweep_rate_hz):g} sweeps/s)"
    )
    t0 = time.perf_counter()
    events, info = simulate(
        scene, rig, sweeps=1, progress=not quiet, return_info=True, key=jr.key(int(rig.seed))
    )
    t_sim = time.perf_counter() - t0
    truth = scene.truth_cube(rig.grid)
    write_events(out / "events.npz", events)
    save_cube(
        out / "truth.npz",
        truth,
        rig.wavelengths_nm,
        labels=scene.labels,
        names=np.array(scene.names, dtype=str),
        threshold_on=info.threshold_on,
        threshold_off=info.threshold_off,
    )
    n_pix = h * w
    raw_bytes = evt3_bytes(events)
    frame_bytes = rig.samples_per_sweep * n_pix
    print(
        f"\nsimulated in {t_sim:.1f} s: {len(events):,} events, "
        f"{len(events) / n_pix:.1f} events/pixel/sweep "
        f"(ON {np.mean(events.p):.0%})"
    )
    print(
        f"bandwidth per sweep: EVT 3.0 file {raw_bytes / 1e3:,.1f} kB "
        f"({8 * raw_bytes / max(len(events), 1):.1f} bits/event), nominal 16 bit/event "
        f"{2 * len(events) / 1e3:,.1f} kB, 8-bit frames ({rig.samples_per_sweep}/sweep) "
        f"{frame_bytes / 1e3:,.1f} kB -> events use "
        f"{100 * 2 * len(events) / frame_bytes:.1f} % of the frame bandwidth"
    )

    # The same sensor (same key: same per-pixel thresholds) looks at the gray chart.
    chart = load_scene("gray-chart", (h, w))
    gray = simulate(chart, rig, sweeps=2, key=jr.key(int(rig.seed)))
    t0 = time.perf_counter()
    cal = calibrate(gray, chart, Rig(), rows_per_label=2)
    save_calibration(out / "calibration.json", cal, comment="evhsi demo, gray chart")
    print(
        f"\ncalibrated from a gray-chart capture ({len(gray):,} events) in "
        f"{time.perf_counter() - t0:.0f} s: thresholds ON {float(cal.rig.threshold_on):.4f} "
        f"OFF {float(cal.rig.threshold_off):.4f}, β {float(cal.rig.beta_nm_per_rad):.2f} "
        f"nm/rad, c {float(cal.rig.baseline_rel):.4f}; per-pixel threshold map RMS error "
        f"{np.sqrt(np.mean((cal.threshold_on_map - info.threshold_on) ** 2)):.5f} "
        f"(true spread {info.threshold_on.std():.4f})"
    )

    rows = {}
    cubes = {}
    variants = [
        ("nominal rig", Rig(), None, None),
        ("calibrated rig + maps", cal.rig, cal.threshold_on_map, cal.threshold_off_map),
        ("true per-pixel thr.*", rig, info.threshold_on, info.threshold_off),
    ]
    for name, r, on, off in variants:
        t0 = time.perf_counter()
        cube = reconstruct(
            events, r, threshold_on_map=on, threshold_off_map=off, progress=not quiet
        )
        dt = time.perf_counter() - t0
        rows[name] = {**evaluate(cube, truth), "seconds": dt}
        cubes[name] = cube
    save_cube(out / "cube.npz", cubes["calibrated rig + maps"], rig.wavelengths_nm)
    save_cube(out / "cube_uncalibrated.npz", cubes["nominal rig"], rig.wavelengths_nm)
    print(
        f"\n{'ColorChecker with':24s} {'SAM deg':>8s} {'PSNR dB':>8s} {'SSIM':>7s} "
        f"{'RMS':>7s} {'time s':>7s}"
    )
    for name, r in rows.items():
        print(
            f"{name:24s} {r['sam_deg']:8.2f} {r['psnr_db']:8.2f} {r['ssim']:7.3f} "
            f"{r['rms']:7.4f} {r['seconds']:7.1f}"
        )
    print(
        "* reference: the simulator's own rig and per-pixel thresholds (a perfect "
        "calibration).\n  Uncalibrated, the ±0.01 threshold mismatch scales each "
        "pixel's spectrum by up to ~±15 % (PSNR drops); the shape (SAM) barely moves."
    )
    panels = {"truth": cube_to_srgb(truth, rig.wavelengths_nm)}
    panels.update({k: cube_to_srgb(v, rig.wavelengths_nm) for k, v in cubes.items()})
    write_comparison_png(out / "comparison.png", panels)
    print(
        f"\nwrote {out}/: events.npz, truth.npz, calibration.json (+ "
        "calibration_thresholds.npz), cube.npz (calibrated), cube_uncalibrated.npz, "
        "comparison.png"
    )
    return rows
