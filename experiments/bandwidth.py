"""Accuracy versus bandwidth: a frame camera against the event camera (paper Fig. 5,
Fig. 11, supplement 7.1).

Setup. The paper's simulated rig (72 channels, 17.5 nm band, 1200 samples per sweep,
30 sweeps/s, c = 3 %) with **no threshold mismatch** (`threshold_sigma = 0`, thresholds
known), one sweep per capture; the mismatch case (σ = 0.01, nominal thresholds in the
reconstruction) is reported beside it. Evaluation scenes: ColorChecker 24×36, rainbow
24×48, metamers 24×48. Training scenes (they alone choose the frame fit's prior, by the
protocol and on the scenes that chose our reconstruction's weights,
experiments/tune_weights.py): `tcs` 12×44 and the synthetic `sharp` set 12×48.

- Ours: `simulate` → `reconstruct` (default solver and weights). Bandwidth: events at 16
  bits (the paper's EVT 3.0 accounting); the exact EVT 3.0 size our writer produces is
  listed too (`ours bw % EVT3`).
- Frame camera: `capture_frames` (instantaneous samples, σ = 0.067 multiplicative noise,
  8 bits, full scale at the peak) → `reconstruct_frames` (linear interpolation, x ≥ 0
  least squares with a spectral prior: kind and weight α from the training scenes).
  1200 frames per sweep is the paper's full bandwidth; 2400–19200 (a camera faster than
  the rig's time grid) are added to locate the crossing when 1200 do not reach our
  accuracy. Bandwidth-matched: as many 8-bit frames as the events' bytes (supplement
  6.5).
- Basis: the ground truth projected onto the 8-vector TCS+RAW2ACES SVD basis (an oracle,
  as the paper evaluates it).
- Crossing: the smallest frame count whose SAM (PSNR) reaches ours, log-linearly
  interpolated between the bracketing counts; our bandwidth as a fraction of those
  frames' bytes is the paper's "40.47 %" figure ("never": not within 19200 frames).

Machine: see the JSON's `machine`; wall times in its `wall_s`.

Run: `.venv/bin/python experiments/bandwidth.py` (`--quick` for a smoke test).
Writes experiments/results/bandwidth.json, bandwidth_fig11.png, bandwidth_fig5.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import jax.random as jr
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _baseline_common import RESULTS, Timer, bl, machine, metrics, table, write_json  # noqa: E402

import evhsi_jax as ev  # noqa: E402

FRAME_COUNTS = (10, 15, 20, 30, 40, 60, 80, 120, 160, 240, 300, 400, 600, 800, 1200)
BEYOND_FULL = (2400, 4800, 9600, 19200)
SCENES = {"colorchecker": (24, 36), "rainbow": (24, 48), "metamers": (24, 48)}
ALPHAS = (1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1, 1.0)
KINDS = ("dct", "d2")
BASIS_SIZE = 8


def rig_with(rig: ev.Rig, **changes) -> ev.Rig:
    return ev.Rig.from_dict({**rig.to_dict(), **changes})


def run_frames(scene, rig, count, prior, key):
    """Capture `count` frames per sweep and reconstruct; a camera faster than the rig's
    time grid gets a rig with a finer grid (same optics)."""
    r = (
        rig
        if count <= rig.samples_per_sweep
        else rig_with(rig, samples_per_sweep=count)
    )
    stack = bl.capture_frames(scene, r, frames=count, key=key)
    kind, alpha = prior
    return stack, bl.reconstruct_frames(stack, r, alpha_spec=alpha, prior_kind=kind)


def crossing(counts, values, target, higher_better):
    """Smallest (log-interpolated) frame count whose value reaches `target`, or None."""
    for i, (c, v) in enumerate(zip(counts, values)):
        if (v >= target) if higher_better else (v <= target):
            if i == 0:
                return float(c)
            c0, v0 = counts[i - 1], values[i - 1]
            f = (target - v0) / (v - v0)
            return float(np.exp(np.log(c0) + f * (np.log(c) - np.log(c0))))
    return None


def training_scenes(quick):
    """The scenes that chose our reconstruction's weights (experiments/tune_weights.py):
    `tcs` and the synthetic `sharp` set — the frame fit is tuned on the same ones."""
    from tune_weights import sharp_scene

    if quick:
        return {"tcs": ev.load_scene("tcs", (8, 22)), "sharp": sharp_scene((4, 24))}
    return {"tcs": ev.load_scene("tcs", (12, 44)), "sharp": sharp_scene((12, 48))}


def tune_prior(rig, scenes, alphas, key):
    """Frame-fit prior (kind, α) with the protocol of tune_weights.py: minimise the mean
    over (scene, frame count) of SAM / best SAM there; counts 1200 and 120."""
    rows = []
    for sname, scene in scenes.items():
        truth = scene.truth_cube(rig.grid)
        for count in (rig.samples_per_sweep, 120):
            stack = bl.capture_frames(scene, rig, frames=count, key=key)
            for kind in KINDS:
                for a in alphas:
                    cube = bl.reconstruct_frames(
                        stack, rig, alpha_spec=a, prior_kind=kind
                    )
                    rows.append(
                        {"scene": sname, "frames": count, "prior": kind, "alpha": a}
                        | metrics(cube, truth)
                    )
    best = {}
    for r in rows:
        k = (r["scene"], r["frames"])
        best[k] = min(best.get(k, np.inf), r["sam_deg"])
    table_rows = []
    for kind in KINDS:
        for a in alphas:
            mine = [r for r in rows if r["prior"] == kind and r["alpha"] == a]
            row = {"prior": kind, "alpha": a}
            for r in mine:
                row[f"SAM {r['scene']}@{r['frames']}"] = r["sam_deg"]
            row["score"] = round(
                float(
                    np.mean(
                        [r["sam_deg"] / best[(r["scene"], r["frames"])] for r in mine]
                    )
                ),
                4,
            )
            table_rows.append(row)
    chosen = min(table_rows, key=lambda r: r["score"])
    return (chosen["prior"], chosen["alpha"]), table_rows, rows


def study_scene(name, size, rig, prior, basis, counts, key, mismatch):
    scene = ev.load_scene(name, size)
    truth = scene.truth_cube(rig.grid)
    h, w = size
    full_bytes = ev.io.frame_bytes(rig.samples_per_sweep, w, h)
    k_ev, k_fr, k_mm = jr.split(key, 3)
    out = {"size": [h, w]}

    with Timer() as t:
        events = ev.simulate(scene, rig, key=k_ev)
        ours = ev.reconstruct(events, rig)
    nominal = ev.io.nominal_event_bytes(len(events), 16)
    out["ours"] = {
        "events": len(events),
        "events_per_pixel": len(events) / (h * w),
        "bytes_nominal16": nominal,
        "bytes_evt3": ev.io.evt3_bytes(events),
        "fraction_of_full": nominal / full_bytes,
        "wall_s": round(t.seconds, 2),
        **metrics(ours, truth),
    }
    if mismatch:
        rig_m = rig_with(rig, threshold_sigma=0.01)
        ev_m = ev.simulate(scene, rig_m, key=k_mm)
        out["ours_mismatch"] = {
            "events": len(ev_m),
            "bytes_nominal16": ev.io.nominal_event_bytes(len(ev_m), 16),
            **metrics(ev.reconstruct(ev_m, rig_m), truth),
        }
    out["basis"] = metrics(np.asarray(bl.basis_project(truth, basis)), truth)

    matched = bl.matched_frame_count(events)
    cubes = {"ours": ours, "basis": np.asarray(bl.basis_project(truth, basis))}
    curve = []
    for count in sorted(set(counts) | {matched}):
        with Timer() as t:
            stack, cube = run_frames(scene, rig, count, prior, k_fr)
        row = {
            "frames": count,
            "bytes": stack.nbytes,
            "fraction_of_full": stack.nbytes / full_bytes,
            "wall_s": round(t.seconds, 2),
            **metrics(cube, truth),
        }
        curve.append(row)
        if count == matched:
            out["matched"] = row
            cubes["frames matched"] = cube
        if count == rig.samples_per_sweep:
            out["full"] = row
            cubes["frames full"] = cube
    out["frames"] = curve
    cs = [r["frames"] for r in curve]
    out["crossing"] = {}
    for key_, better_high in (("sam_deg", False), ("psnr_db", True)):
        f_star = crossing(cs, [r[key_] for r in curve], out["ours"][key_], better_high)
        out["crossing"][key_] = {
            "frames": f_star,
            "our_fraction": None if f_star is None else nominal / (f_star * h * w),
        }
    return out, scene, truth, cubes


def red_end_artifact(truth, cubes, wl):
    """Rainbow diagnostic: on the `peak` rows (top third), over pixels whose truth is
    dark (≤ 0.05) in every channel above 720 nm, the mean of each estimate's maximum
    there — a spurious red peak shows as a large value."""
    red = wl > 720.0
    top = truth[: truth.shape[0] // 3]
    dark = np.all(top[..., red] <= 0.05, axis=-1)
    return {
        k: round(float(np.mean(c[: truth.shape[0] // 3][..., red].max(-1)[dark])), 4)
        for k, c in {"truth": truth, **cubes}.items()
    }


def prior_sensitivity(rig, size, prior, key):
    """Rainbow only: both methods' spectral-prior weights around their defaults.

    Not a tuning (the evaluation scene must not choose weights); it shows how much of
    each method's rainbow error is its smoothness prior.
    """
    scene = ev.load_scene("rainbow", size)
    truth = scene.truth_cube(rig.grid)
    k_ev, k_fr = jr.split(key)
    events = ev.simulate(scene, rig, key=k_ev)
    base = ev.reconstruction.ProblemConfig()
    rows = []
    for f in (100.0, 10.0, 1.0, 0.1):
        cfg = dataclasses.replace(base, alpha_spec=base.alpha_spec * f)
        cube = ev.reconstruct(events, rig, config=cfg)
        rows.append(
            {"method": f"ours ({base.spec_kind})", "alpha": cfg.alpha_spec}
            | metrics(cube, truth)
        )
    stack = bl.capture_frames(
        scene, rig, frames=bl.matched_frame_count(events), key=k_fr
    )
    kind, alpha = prior
    for f in (100.0, 10.0, 1.0, 0.1):
        cube = bl.reconstruct_frames(stack, rig, alpha_spec=alpha * f, prior_kind=kind)
        rows.append(
            {"method": f"frames matched ({stack.count}, {kind})", "alpha": alpha * f}
            | metrics(cube, truth)
        )
    return rows


def fig11(path, results, full_frames):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(2, len(names), figsize=(4.2 * len(names), 6.5))
    axes = np.atleast_2d(axes).reshape(2, len(names))
    for j, name in enumerate(names):
        r = results[name]
        x = [c["fraction_of_full"] for c in r["frames"]]
        for i, (k, lab) in enumerate(
            (("sam_deg", "SAM (deg)"), ("psnr_db", "PSNR (dB)"))
        ):
            ax = axes[i, j]
            ax.plot(x, [c[k] for c in r["frames"]], "o-", ms=3, label="frame camera")
            ax.plot(
                r["ours"]["fraction_of_full"], r["ours"][k], "r*", ms=14, label="ours"
            )
            if "ours_mismatch" in r:
                fm = r["ours_mismatch"]["bytes_nominal16"] / (
                    full_frames * r["size"][0] * r["size"][1]
                )
                ax.plot(
                    fm,
                    r["ours_mismatch"][k],
                    "r*",
                    mfc="none",
                    ms=12,
                    label="ours, threshold mismatch",
                )
            ax.axhline(r["basis"][k], color="g", ls="--", lw=1, label="basis (oracle)")
            ax.axvline(1.0, color="k", ls=":", lw=0.8)
            ax.set_xscale("log")
            ax.set_xlabel("bandwidth / full-bandwidth frames (1200 × 8 bit)")
            ax.set_ylabel(lab)
            if i == 0:
                ax.set_title(name)
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig5(path, scene, truth, cubes, wl):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = {"truth": truth, **cubes}
    n = len(panels)
    fig = plt.figure(figsize=(3.0 * n, 7.5), layout="constrained")
    for i, (title, cube) in enumerate(panels.items()):
        ax = fig.add_subplot(3, n, i + 1)
        ax.imshow(ev.cube_to_srgb(cube, wl), interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    h, w = truth.shape[:2]
    for j, (row, label) in enumerate(
        ((h // 6, "peak"), (h // 2, "step"), (5 * h // 6, "notch"))
    ):
        for k, col in enumerate((w // 4, 3 * w // 4)):
            ax = fig.add_subplot(3, 4, 5 + 4 * (j // 2) + 2 * (j % 2) + k)
            for title, cube in panels.items():
                ax.plot(
                    wl,
                    cube[row, col],
                    lw=2.0 if title == "truth" else 1.0,
                    color="k" if title == "truth" else None,
                    label=title,
                )
            ax.set_title(f"{label}, column {col}", fontsize=8)
            ax.tick_params(labelsize=7)
            if j == 0 and k == 0:
                ax.legend(fontsize=6)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--quick", action="store_true", help="small sizes, few frame counts"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    t_all = time.perf_counter()
    rig = ev.Rig(threshold_sigma=0.0)
    key = jr.key(args.seed)
    if args.quick:
        scenes = {"colorchecker": (8, 12), "rainbow": (6, 16)}
        counts, alphas = (20, 120, 1200), (1e-4, 3e-3)
    else:
        scenes, counts, alphas = SCENES, FRAME_COUNTS + BEYOND_FULL, ALPHAS

    with Timer() as t_tune:
        prior, tune_table, tune_rows = tune_prior(
            rig, training_scenes(args.quick), alphas, jr.fold_in(key, 99)
        )
    print(
        table(
            tune_table,
            list(tune_table[0]),
            "Frame fit: prior kind and weight α on the training scenes tcs and sharp "
            "(σ = 0.067, 8 bit; score = mean SAM / best SAM)",
        )
    )
    print(
        f"chosen prior {prior[0]}, α = {prior[1]:g} (library default "
        f"{bl.FRAME_PRIOR_KIND}, {bl.FRAME_ALPHA_SPEC:g}); {t_tune.seconds:.0f} s\n"
    )

    basis = bl.reflectance_basis(rig.grid, BASIS_SIZE)
    print(
        f"basis: {basis.name}, {basis.size} vectors from {basis.training_size} "
        f"spectra, {100 * basis.energy:.2f} % of the training energy\n"
    )
    results, fig5_data = {}, None
    for i, (name, size) in enumerate(scenes.items()):
        with Timer() as t:
            r, scene, truth, cubes = study_scene(
                name,
                size,
                rig,
                prior,
                basis,
                counts,
                jr.fold_in(key, i),
                mismatch=not args.quick,
            )
        r["wall_s"] = round(t.seconds, 1)
        results[name] = r
        if name == "rainbow":
            fig5_data = (scene, truth, cubes)
            r["red_end_artifact"] = red_end_artifact(truth, cubes, rig.wavelengths_nm)
            print(
                "rainbow peak row, pixels dark (truth ≤ 0.05) above 720 nm: mean of the "
                f"max estimate there: {r['red_end_artifact']}"
            )
        print(
            table(
                r["frames"],
                [
                    "frames",
                    "bytes",
                    "fraction_of_full",
                    "sam_deg",
                    "psnr_db",
                    "ssim",
                    "rms",
                    "wall_s",
                ],
                f"{name} {size[0]}x{size[1]}: frame camera vs frame count",
            )
        )
        print(f"ours: {r['ours']}\n")

    summary = []
    for name, r in results.items():
        o, m, f, b = r["ours"], r["matched"], r.get("full", {}), r["basis"]
        cs, cp = r["crossing"]["sam_deg"], r["crossing"]["psnr_db"]
        summary.append(
            {
                "scene": name,
                "ours SAM": o["sam_deg"],
                "ours PSNR": o["psnr_db"],
                "ev/px": round(o["events_per_pixel"], 1),
                "ours bw %": round(100 * o["fraction_of_full"], 2),
                "ours bw % EVT3": round(
                    100
                    * o["bytes_evt3"]
                    / o["bytes_nominal16"]
                    * o["fraction_of_full"],
                    2,
                ),
                "matched F": m["frames"],
                "matched SAM": m["sam_deg"],
                "matched PSNR": m["psnr_db"],
                "full SAM": f.get("sam_deg", ""),
                "full PSNR": f.get("psnr_db", ""),
                "basis SAM": b["sam_deg"],
                "basis PSNR": b["psnr_db"],
                "F*(SAM)": "never" if cs["frames"] is None else round(cs["frames"]),
                "ours/F*(SAM) %": "-"
                if cs["frames"] is None
                else round(100 * cs["our_fraction"], 1),
                "F*(PSNR)": "never" if cp["frames"] is None else round(cp["frames"]),
                "ours/F*(PSNR) %": "-"
                if cp["frames"] is None
                else round(100 * cp["our_fraction"], 1),
            }
        )
    print(
        table(
            summary,
            list(summary[0]),
            "Summary (bandwidth: events at 16 bits vs 8-bit "
            "frames; full = 1200 frames/sweep)",
        )
    )
    if not args.quick:
        mm = [
            {
                "scene": n,
                **{
                    k: r["ours_mismatch"][k]
                    for k in ("events", "sam_deg", "psnr_db", "ssim", "rms")
                },
            }
            for n, r in results.items()
        ]
        print(
            table(
                mm,
                list(mm[0]),
                "Ours with threshold mismatch σ = 0.01 "
                "(nominal thresholds in the reconstruction)",
            )
        )

    sens = []
    if not args.quick:
        with Timer() as t_sens:
            sens = prior_sensitivity(rig, SCENES["rainbow"], prior, jr.fold_in(key, 1))
        print(
            table(
                sens,
                ["method", "alpha", "sam_deg", "psnr_db", "ssim", "rms"],
                f"Rainbow: spectral-prior weight sensitivity ({t_sens.seconds:.0f} s; "
                f"defaults: ours {ev.reconstruction.ProblemConfig().alpha_spec:g}, "
                f"frames {prior[1]:g},"
                " both chosen on tcs + sharp)",
            )
        )

    args.out.mkdir(parents=True, exist_ok=True)
    stem = "bandwidth_quick" if args.quick else "bandwidth"
    fig11(args.out / f"{stem}_fig11.png", results, rig.samples_per_sweep)
    if fig5_data is not None:
        fig5(args.out / f"{stem}_fig5.png", *fig5_data, rig.wavelengths_nm)
    wall = round(time.perf_counter() - t_all, 1)
    write_json(
        args.out / f"{stem}.json",
        {
            "setup": {
                "rig": "paper defaults, threshold_sigma=0",
                "sweeps": 1,
                "frame_noise_sigma": bl.FRAME_NOISE_SIGMA,
                "frame_bits": 8,
                "bits_per_event": 16,
                "frame_prior": {"kind": prior[0], "alpha": prior[1]},
                "ours_config": dataclasses.asdict(ev.reconstruction.ProblemConfig()),
                "basis_size": BASIS_SIZE,
                "basis": basis.name,
                "basis_training_size": basis.training_size,
                "basis_energy": basis.energy,
                "seed": args.seed,
            },
            "prior_tuning": tune_table,
            "prior_tuning_runs": tune_rows,
            "prior_tuning_wall_s": round(t_tune.seconds, 1),
            "scenes": results,
            "summary": summary,
            "rainbow_prior_sensitivity": sens,
            "machine": machine(),
            "wall_s": wall,
        },
    )
    print(f"wall time {wall} s; wrote {args.out}/{stem}.json and PNGs")
    return results


if __name__ == "__main__":
    main()
