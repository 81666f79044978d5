"""Ablation of the reconstruction's terms (paper Fig. 3) and of our changes to them.

Variants: (a) no non-negativity, (b) no spectral prior, (c) weak anti-drift
(α_int / 100), (d) full method; plus the paper-literal objective (no normalisation,
straight-line anti-drift, DCT prior), straight-line instead of flat-peak anti-drift,
DCT instead of second-difference prior, and the unconstrained SVD solution (Eq. 15).

Setup: paper rig (threshold mismatch σ = 0.01, refractory 50 µs), one sweep;
ColorChecker 48×72 and rainbow 48×96, reconstructed with the sensor's per-pixel
thresholds (as after calibration) and the exact solver.
Run: `.venv/bin/python experiments/ablation.py` (about 3 min on 2 cores).
"""

import dataclasses

from _common import capture, pyplot, save, timed_reconstruct

import evhsi_jax as ev


def variants():
    full = ev.reconstruction.ProblemConfig()
    return {
        "(a) no non-negativity": (full, "unconstrained"),
        "(b) no spectral prior": (dataclasses.replace(full, alpha_spec=0.0), "auto"),
        "(c) weak anti-drift": (
            dataclasses.replace(full, alpha_int=full.alpha_int / 100),
            "auto",
        ),
        "(d) full method": (full, "auto"),
        "paper-literal terms": (
            dataclasses.replace(
                full,
                normalise=False,
                int_target="linear",
                spec_kind="dct",
                alpha_int=1.0,
                alpha_spec=1.0,
            ),
            "auto",
        ),
        "straight-line anti-drift": (
            dataclasses.replace(full, int_target="linear"),
            "auto",
        ),
        "DCT spectral prior": (dataclasses.replace(full, spec_kind="dct"), "auto"),
        "SVD (paper Eq. 15)": (full, "svd"),
    }


def main():
    results = {}
    cubes = {}
    for scene_name, size in (("colorchecker", (48, 72)), ("rainbow", (48, 96))):
        rig, scene, events, info, truth = capture(scene_name, size)
        for label, (cfg, solver) in variants().items():
            cube, dt = timed_reconstruct(events, rig, info, config=cfg, solver=solver)
            m = ev.evaluate(cube, truth)
            results.setdefault(scene_name, {})[label] = {**m, "seconds": dt}
            cubes[(scene_name, label)] = (cube, truth, scene, rig)
            print(
                f"{scene_name:12s} {label:26s} SAM {m['sam_deg']:6.2f}  PSNR "
                f"{m['psnr_db']:6.2f}  SSIM {m['ssim']:.3f}",
                flush=True,
            )
    print("\n| variant | ColorChecker SAM° | PSNR dB | rainbow SAM° | PSNR dB |")
    print("|---|---:|---:|---:|---:|")
    for label in variants():
        a, b = results["colorchecker"][label], results["rainbow"][label]
        print(
            f"| {label} | {a['sam_deg']:.2f} | {a['psnr_db']:.2f} | "
            f"{b['sam_deg']:.2f} | {b['psnr_db']:.2f} |"
        )
    plt = pyplot()
    fig, axes = plt.subplots(2, 4, figsize=(14, 6))
    labels = list(variants())[:4]
    for row, scene_name in enumerate(("colorchecker", "rainbow")):
        for ax, label in zip(axes[row], labels):
            cube, truth, scene, rig = cubes[(scene_name, label)]
            wl = rig.wavelengths_nm
            picks = [0, scene.height * scene.width // 2 + scene.width // 3]
            for p, col in zip(picks, ("C0", "C3")):
                y, x = divmod(p, scene.width)
                ax.plot(wl, truth[y, x], col + "--", lw=1)
                ax.plot(wl, cube[y, x], col, lw=1)
            ax.set_title(f"{scene_name}: {label}", fontsize=8)
    fig.tight_layout()
    save("ablation", {"setup": __doc__, "results": results}, fig)


if __name__ == "__main__":
    main()
