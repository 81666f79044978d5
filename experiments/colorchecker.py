"""ColorChecker evaluation (paper Fig. 6): overall and per-patch accuracy, several seeds.

Setup: the paper's simulated rig (DESIGN.md defaults: 72 channels 400–760 nm, FWHM
17.5 nm, 1200 samples/sweep, 30 sweeps/s, c = 3 %, C ~ N(0.15, 0.01) per pixel,
refractory 50 µs), one sweep, ColorChecker 96×144 (24 patches of 24×24 px), seeds
0…4 (a new sensor — thresholds — each). Reconstructions: with nominal thresholds, and
with the sensor's per-pixel thresholds (what a per-pixel threshold calibration gives).
Metrics are per-pixel means over all pixels (SAM) and over the whole cube (PSNR, RMS).

Run: `.venv/bin/python experiments/colorchecker.py [--seeds 5] [--size 96x144]`
(about 2 min on 2 cores).
"""

import argparse

import numpy as np
from _common import capture, pyplot, save, timed_reconstruct

import evhsi_jax as ev


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--size", default="96x144")
    args = ap.parse_args()
    size = ev.forward.parse_size(args.size)
    runs = {"nominal": [], "per-pixel": []}
    patch_rows = []
    for seed in range(args.seeds):
        rig, scene, events, info, truth = capture("colorchecker", size, seed=seed)
        for mode in runs:
            cube, dt = timed_reconstruct(
                events, rig, info if mode == "per-pixel" else None
            )
            m = ev.evaluate(cube, truth)
            runs[mode].append(
                {
                    **m,
                    "seconds": dt,
                    "seed": seed,
                    "events_per_px": len(events) / (size[0] * size[1]),
                }
            )
            if mode == "per-pixel":
                patch_rows.append(
                    ev.metrics.per_label_table(cube, truth, scene.labels, scene.names)
                )
                last = (cube, truth, scene, rig)
            print(
                f"seed {seed} {mode:9s} SAM {m['sam_deg']:.2f} PSNR {m['psnr_db']:.2f} "
                f"SSIM {m['ssim']:.3f} RMS {m['rms']:.4f} ({dt:.1f} s)",
                flush=True,
            )
    summary = {}
    for mode, rs in runs.items():
        summary[mode] = {
            k: {
                "mean": float(np.mean([r[k] for r in rs])),
                "sd": float(np.std([r[k] for r in rs])),
            }
            for k in ("sam_deg", "psnr_db", "ssim", "rms")
        }
    print("\n| thresholds | SAM° | PSNR dB | SSIM | RMS |\n|---|---:|---:|---:|---:|")
    for mode, s in summary.items():
        print(
            f"| {mode} | {s['sam_deg']['mean']:.2f} ± {s['sam_deg']['sd']:.2f} | "
            f"{s['psnr_db']['mean']:.2f} ± {s['psnr_db']['sd']:.2f} | "
            f"{s['ssim']['mean']:.3f} | {s['rms']['mean']:.4f} |"
        )
    print("| paper (Fig. 6) | 21.05 | 28.46 | – | 0.204 |")
    per_patch = [
        {
            "name": patch_rows[0][i]["name"],
            "sam_deg": float(np.mean([pr[i]["sam_deg"] for pr in patch_rows])),
            "rms": float(np.mean([pr[i]["rms"] for pr in patch_rows])),
        }
        for i in range(len(patch_rows[0]))
    ]
    cube, truth, scene, rig = last
    plt = pyplot()
    fig, axes = plt.subplots(4, 6, figsize=(15, 9), sharex=True, sharey=True)
    wl = rig.wavelengths_nm
    for lab, ax in enumerate(axes.ravel()):
        sel = scene.labels == lab
        ax.plot(wl, truth[sel].mean(0), "k--", lw=1)
        ax.plot(wl, cube[sel].mean(0), "C3", lw=1)
        ax.fill_between(
            wl,
            np.percentile(cube[sel], 5, 0),
            np.percentile(cube[sel], 95, 0),
            color="C3",
            alpha=0.2,
        )
        ax.set_title(
            f"{scene.names[lab][:18]} SAM {per_patch[lab]['sam_deg']:.1f}°", fontsize=7
        )
    fig.tight_layout()
    save(
        "colorchecker",
        {"setup": __doc__, "summary": summary, "runs": runs, "per_patch": per_patch},
        fig,
    )


if __name__ == "__main__":
    main()
