"""Realism study: the pipeline on captures from a sensor with real effects.

Setup (a user's procedure, nothing taken from the truth): for each sensor, simulate a
gray-chart capture (32 sweeps, about one second) and calibrate from it with
`evhsi_jax.calibrate` starting from the default rig plus what a user knows of their
hardware — the band profile (measured once with a spectrometer; in the rows "…, not
given" and "…, band not given" the user gives none and the calibration fits it, its
default since 2026-11-28, before which those rows showed what leaving it out cost;
"shouldered" is a band outside the preset's skew-normal family). The photoreceptor's
cut-off is measured by the calibration (since 2026-11-28; `--cutoff given` gives it
in the initial rig and keeps it, the setup of the tables before; `--cutoff none`
neither gives nor measures it, what a user who did not know it got before); then
simulate the
held-out scene with the *same* sensor (same seed: same pixels, thresholds and hot
pixels), one sweep and four sweeps (a static scene recorded for ~0.13 s; more with
`--held-out-sweeps`, e.g. 1,4,8,16), and reconstruct it

- "old": the wave-1 reconstruction — the calibrated rig and threshold maps, every event
  an exact constraint (the sensor keys of the calibration ignored), every sweep at the
  calibration's mirror speed (`sweep_speed="off"`);
- "new": `evhsi_jax.reconstruct(events, calibration)` — noise-weighted rows, photo-
  receptor delay compensation, robust reweighting, screening of noise events and hot
  pixels, output bounded to [0, 1.5].

The held-out scene is the ColorChecker (measured reflectances); the reconstruction's
weights were chosen on the `tcs` training scene. Metrics are against the scene's
reflectance and, in the last column, against the scene seen through the optics (the
true PSF applied: what reaches the pixels; a per-pixel method cannot undo the blur).
Each effect alone at three magnitudes, the issue's "moderate mix" and the `realistic`
preset. A second table splits the new reconstruction's PSNR between the channels the
lamp lights above the constant light c and the dim red end (`lit_channels`).

Run: `.venv/bin/python experiments/realism.py [--size 32x48] [--quick]`
→ experiments/results/realism.json and realism.png. Machine: the 2-core CI VM.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.random as jr
import numpy as np
from _common import white_response

import evhsi_jax as ev

EFFECTS = {
    "threshold_noise": [0.005, 0.01, 0.025],
    "timestamp_jitter_us": [2.0, 5.0, 15.0],
    "photoreceptor_hz": [30000.0, 10000.0, 3000.0],
    "noise_rate_hz": [0.3, 1.0, 3.0],
    "hot_pixel_fraction": [0.0005, 0.001, 0.003],
    "band_profile": ["skewed", "shouldered"],
    "sweep_curvature_nm": [1.0, 3.0, 6.0],
    "sweep_rate_jitter": [0.001, 0.002, 0.005],
    "psf_sigma_px": [0.3, 0.5, 1.0],
    "on_off_correlation": [0.8, 0.5, 0.0],
}
DEFAULT_MAGNITUDE = {  # the `realistic` preset's value of each effect
    k: v for k, v in ev.forward.SENSOR_PRESETS["realistic"].items() if k in EFFECTS
}
MODERATE_MIX = {
    "threshold_noise": 0.01,
    "timestamp_jitter_us": 5.0,
    "photoreceptor_hz": 10000.0,
    "noise_rate_hz": 1.0,
    "hot_pixel_fraction": 0.001,
    "band_profile": "skewed",
    "sweep_curvature_nm": 3.0,
    "sweep_rate_jitter": 0.002,
}


def shouldered_band(fwhm_nm: float) -> dict:
    """A band outside the skew-normal family of the `realistic` preset: a Gaussian
    with a shoulder on its red side (35 % of the peak, 0.6 FWHM out, 0.7 times as
    wide), as a rig's `band_profile` (the same as `tests/calibration/test_band_fit.py`)."""
    off = np.linspace(-3 * fwhm_nm, 3 * fwhm_nm, 161)
    s = fwhm_nm / 2.3548
    val = np.exp(-(off**2) / (2 * s**2)) + 0.35 * np.exp(
        -((off - 0.6 * fwhm_nm) ** 2) / (2 * (0.7 * s) ** 2)
    )
    return {"offset_nm": off.tolist(), "values": (val / val.max()).tolist()}


def sensor_keys(sensor: dict) -> dict:
    """A case's rig keys, the named "shouldered" band as its profile."""
    if sensor.get("band_profile") == "shouldered":
        fwhm = float(ev.Rig.from_dict(sensor | {"band_profile": None}).fwhm_nm)
        return sensor | {"band_profile": shouldered_band(fwhm)}
    return sensor


CHART_SWEEPS = 32  # gray-chart capture: about one second on the paper's rig (8 before:
# the threshold maps averaged too little crossing noise; README "Real sensors")
HELD_OUT_SWEEPS = (1, 4)  # the held-out scene, one sweep and a short static recording


def user_init(true: ev.Rig, band_known: bool = True, cutoff: str = "measured") -> ev.Rig:
    """What a user puts in `--init`: the band profile (measured once with a
    spectrometer) and, with `cutoff="given"`, the photoreceptor cut-off; everything
    else is the default rig."""
    init = {}
    if cutoff == "given" and true.effects.photoreceptor_hz > 0:
        init["photoreceptor_hz"] = true.effects.photoreceptor_hz
    if band_known and true.band_profile is not None:
        init["band_profile"] = {
            "offset_nm": list(true.band_profile[0]),
            "values": list(true.band_profile[1]),
        }
    return ev.Rig.from_dict(init)


def lit_channels(rig: ev.Rig) -> np.ndarray:
    """Channels the lamp lights: the band centred on the channel gives a white pixel
    at least the constant light c (A(λc) ≥ c, the rainbow study's rule). Beyond it the
    lamp times D(λ) falls below c: a reflectance there moves the log level by less than
    a threshold on its own, so with a noisy sensor those channels are filled by the
    priors."""
    a = white_response(rig, np.asarray(rig.grid.centres_nm))
    return a >= float(rig.baseline_rel)


def split_psnr(cube, truth, lit) -> tuple[float, float]:
    """PSNR (dB) over the lit channels and over the rest."""
    err = (np.asarray(cube, np.float64) - np.asarray(truth, np.float64)) ** 2
    return tuple(float(-10 * np.log10(err[..., sel].mean())) for sel in (lit, ~lit))


def run_case(
    sensor: dict,
    size,
    seed: int,
    band_known: bool = True,
    chart_sweeps: int = CHART_SWEEPS,
    true_maps: bool = False,
    cutoff: str = "measured",
    band: str = "auto",
    held_out_sweeps=HELD_OUT_SWEEPS,
) -> dict:
    h, w = size
    chart = ev.load_scene("gray-chart", (h, w))
    scene = ev.load_scene("colorchecker", (h, w))
    true = ev.Rig.from_dict(sensor_keys(sensor))
    key = jr.key(seed)
    gray = ev.simulate(chart, true, sweeps=chart_sweeps, key=key)
    truth = scene.truth_cube(true.grid)
    # What reaches the sensor: the scene through the optics (the same cube when the
    # sensor has no PSF). `reconstruct` deblurs by the calibrated PSF (a Wiener filter:
    # part of the blur is undone, the rest is lost to noise).
    optics = scene.blurred(float(true.effects.psf_sigma_px)).truth_cube(true.grid)
    t0 = time.perf_counter()
    try:
        res = ev.calibrate(
            gray,
            chart,
            user_init(true, band_known, cutoff),
            fit_photoreceptor=cutoff == "measured",
            fit_band=None if band == "auto" else False,
        )
    except ValueError as err:
        return {"error": str(err)}
    cal = res.calibration
    old = ev.Calibration(  # (no sensor keys: no noise model, as in wave 1)
        res.rig.replace_host(**ev.Rig().effects.as_dict(), noise_rate_hz=0.0),
        res.threshold_on_map,
        res.threshold_off_map,
    )
    out = {"calibration_s": time.perf_counter() - t0, "measured": cal.report}
    lit = lit_channels(cal.rig)
    for sweeps in held_out_sweeps:
        events, info = ev.simulate(
            scene, true, sweeps=sweeps, key=key, return_info=True
        )
        variants = [("old", old), ("new", cal)]
        if true_maps:  # what the calibration's maps cost: the same rig, the true maps
            variants.append(("new_true_maps", dataclasses.replace(
                cal, threshold_on=info.threshold_on, threshold_off=info.threshold_off
            )))  # fmt: skip
        for name, c in variants:
            if name == "old" and sweeps != 1:
                continue
            t1 = time.perf_counter()
            # (wave 1 read every sweep at the calibration's mirror speed)
            speed = "off" if name == "old" else "auto"
            cube = ev.reconstruct(events, c, sweep_speed=speed)
            m = ev.evaluate(cube, truth)
            mo = ev.evaluate(cube, optics)
            psnr_lit, psnr_dim = split_psnr(cube, truth, lit)
            out[name if sweeps == 1 else f"{name}_{sweeps}"] = {
                "sam_deg": m["sam_deg"],
                "psnr_db": m["psnr_db"],
                "optics_sam_deg": mo["sam_deg"],
                "optics_psnr_db": mo["psnr_db"],
                "psnr_lit_db": psnr_lit,  # channels lit above c (lit_channels)
                "psnr_dim_db": psnr_dim,  # the rest (the red end)
                "lit_channels": int(lit.sum()),
                "min": float(cube.min()),
                "max": float(cube.max()),
                "seconds": time.perf_counter() - t1,
            }
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="32x48")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="default magnitudes only")
    ap.add_argument("--out", default="experiments/results/realism.json")
    ap.add_argument(
        "--table", metavar="JSON", help="print the markdown table of a finished run"
    )
    ap.add_argument(
        "--only",
        help="comma-separated effect names to run (e.g. 'realistic preset'); "
        "semicolon-separated when a name has a comma ('band_profile, not given;ideal')",
    )
    ap.add_argument(
        "--true-maps",
        action="store_true",
        help="also reconstruct with the sensor's true threshold maps (calibrated rig)",
    )
    ap.add_argument(
        "--chart-sweeps",
        type=int,
        default=CHART_SWEEPS,
        help=f"sweeps of the gray-chart capture (default {CHART_SWEEPS} ≈ 1 s)",
    )
    ap.add_argument(
        "--cutoff",
        choices=("measured", "given", "none"),
        default="measured",
        help="the photoreceptor cut-off: measured by the calibration (default), "
        "given in the initial rig and kept (the setup before it was measured), or "
        "neither (kept at 0: what a user who did not know it got before)",
    )
    ap.add_argument(
        "--band",
        choices=("auto", "keep"),
        default="auto",
        help="the band profile: the calibration's default (fitted when the user gives "
        "none) or kept as given (the Gaussian of the default rig when not given: what "
        "a user got before 2026-11-28)",
    )
    ap.add_argument(
        "--held-out-sweeps",
        default=",".join(str(v) for v in HELD_OUT_SWEEPS),
        help="sweeps of the held-out recordings, comma-separated, 1 and 4 among them "
        "(default %(default)s; e.g. 1,4,8,16: a longer static recording, each "
        "reported as new_N)",
    )
    args = ap.parse_args(argv)
    held_out = tuple(int(v) for v in args.held_out_sweeps.split(","))
    if not {1, 4} <= set(held_out):
        ap.error("--held-out-sweeps must include 1 and 4 (the tables' columns)")
    ev.enable_compilation_cache()  # each sensor's programs; the caches are cleared below
    if args.table:
        rows = json.loads(Path(args.table).read_text())["rows"]
        print(markdown(rows))
        print(markdown_split(rows))
        return
    size = tuple(int(v) for v in args.size.split("x"))
    cases = [("ideal", None, {})]
    for k, mags in EFFECTS.items():
        for v in mags:
            if args.quick and v != DEFAULT_MAGNITUDE.get(k):
                continue
            cases.append((k, v, {k: v}))
    # Without the band profile in the initial rig: the calibration fits it (since
    # 2026-11-28; before, it kept the Gaussian of the default rig).
    for band in EFFECTS["band_profile"]:
        cases.append(("band_profile, not given", band, {"band_profile": band}))
    cases.append(("moderate mix", None, MODERATE_MIX))
    cases.append(("realistic preset", None, {"sensor": "realistic"}))
    cases.append(("moderate mix, band not given", None, MODERATE_MIX))
    cases.append(("realistic preset, band not given", None, {"sensor": "realistic"}))
    if args.only:
        sep = ";" if ";" in args.only else ","  # (';' for names with commas)
        wanted = {v.strip() for v in args.only.split(sep)}
        cases = [c for c in cases if c[0] in wanted]
    rows = []
    for name, mag, sensor in cases:
        r = run_case(
            sensor,
            size,
            args.seed,
            band_known="not given" not in name,
            chart_sweeps=args.chart_sweeps,
            true_maps=args.true_maps,
            cutoff=args.cutoff,
            band=args.band,
            held_out_sweeps=held_out,
        )
        # Each sensor compiles its own programs; a 30-case run in one process ran out
        # of LLVM code memory without this.
        jax.clear_caches()
        rows.append({"effect": name, "magnitude": mag, "sensor": sensor, **r})
        if "error" in r:
            print(f"{name:22s} {mag!s:>8s}  calibration refused: {r['error']}")
            continue
        o, n, n4 = r["old"], r["new"], r["new_4"]
        print(
            f"{name:22s} {mag!s:>8s}  old {o['sam_deg']:6.2f}° {o['psnr_db']:7.2f} dB  "
            f"new {n['sam_deg']:6.2f}° {n['psnr_db']:7.2f} dB  "
            f"4 sweeps {n4['sam_deg']:6.2f}° {n4['psnr_db']:7.2f} dB "
            f"(optics {n4['optics_sam_deg']:5.2f}° {n4['optics_psnr_db']:6.2f} dB)  "
            f"[{n['min']:.2f}, {n['max']:.2f}]  lit/dim channels 1 sweep "
            f"{n['psnr_lit_db']:.2f}/{n['psnr_dim_db']:.2f} dB, 4 sweeps "
            f"{n4['psnr_lit_db']:.2f}/{n4['psnr_dim_db']:.2f} dB"
            + "".join(
                f"; {s} sweeps {r[f'new_{s}']['sam_deg']:.2f}° "
                f"{r[f'new_{s}']['psnr_db']:.2f} dB"
                for s in held_out
                if s not in (1, 4)
            )
            + "".join(
                f"  true maps {sw}: {r[k]['sam_deg']:.2f}° {r[k]['psnr_db']:.2f} dB"
                for sw, k in (("1", "new_true_maps"), ("4", "new_true_maps_4"))
                if k in r
            ),
            flush=True,
        )
    result = {
        "setup": {
            "size": list(size),
            "seed": args.seed,
            "calibration": f"gray-chart, {args.chart_sweeps} sweeps, ev.calibrate from the "
            "default rig + the user's band profile (rows 'not given': fitted)"
            + {
                "measured": "; the photoreceptor cut-off measured",
                "given": " and photoreceptor cut-off (kept)",
                "none": "; no photoreceptor cut-off (neither given nor measured)",
            }[args.cutoff],
            "held_out_scene": "colorchecker, 1 and 4 sweeps, same sensor; metrics "
            "against the scene and against the scene seen through the optics (PSF)",
        },
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    _plot(rows, out.with_suffix(".png"))
    print(markdown(rows))
    print(markdown_split(rows))
    print(f"wrote {out}")


def markdown(rows) -> str:
    """The README's table: old and new SAM / PSNR, the new cube's value range, and the
    new reconstruction of 4 sweeps (against the scene, and against what the optics
    delivered)."""
    lines = [
        "| effect | magnitude | old, 1 sweep SAM° / PSNR dB | new, 1 sweep | new range "
        "| new, 4 sweeps | 4 sweeps vs optics |",
        "|---|---:|---:|---:|---|---:|---:|",
    ]
    for r in rows:
        mag = "" if r["magnitude"] is None else r["magnitude"]
        if "error" in r:
            lines.append(f"| {r['effect']} | {mag} | calibration refused | | | | |")
            continue
        o, n, n4 = r["old"], r["new"], r["new_4"]
        lines.append(
            f"| {r['effect']} | {mag} | {o['sam_deg']:.2f} / {o['psnr_db']:.2f} | "
            f"**{n['sam_deg']:.2f} / {n['psnr_db']:.2f}** | "
            f"[{n['min']:.2f}, {n['max']:.2f}] | "
            f"{n4['sam_deg']:.2f} / {n4['psnr_db']:.2f} | "
            f"{n4['optics_sam_deg']:.2f} / {n4['optics_psnr_db']:.2f} |"
        )
    return "\n".join(lines)


def markdown_split(rows) -> str:
    """PSNR of the new reconstruction over the channels the lamp lights above the
    constant light c and over the dim rest (`lit_channels`), 1 and 4 sweeps."""
    lines = [
        "| effect | magnitude | lit channels | 1 sweep: all / lit / dim dB "
        "| 4 sweeps: all / lit / dim dB |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "error" in r or "psnr_lit_db" not in r["new"]:
            continue
        mag = "" if r["magnitude"] is None else r["magnitude"]
        cells = [
            f"{n['psnr_db']:.2f} / {n['psnr_lit_db']:.2f} / {n['psnr_dim_db']:.2f}"
            for n in (r["new"], r["new_4"])
        ]
        lines.append(
            f"| {r['effect']} | {mag} | {r['new']['lit_channels']} | "
            f"{cells[0]} | {cells[1]} |"
        )
    return "\n".join(lines)


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 5, figsize=(18, 7))
    for ax, k in zip(axes.ravel(), EFFECTS):
        sel = [r for r in rows if r["effect"] == k and "new" in r]
        if not sel:
            continue
        xs = list(range(len(sel)))
        for lab, style in (("old", "o--"), ("new", "s-"), ("new_4", "^-")):
            ax.plot(xs, [r[lab]["psnr_db"] for r in sel], style, label=lab)
        ax.set_xticks(xs, [str(r["magnitude"]) for r in sel])
        ax.set_title(k)
        ax.set_ylabel("PSNR dB")
        ax.axhline(28, color="gray", lw=0.5)
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=80)


if __name__ == "__main__":
    main()
