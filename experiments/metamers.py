"""Metamer pairs (paper Fig. 7): are spectra with the same sRGB told apart?

Setup: paper rig, one sweep, the `metamers` scene 48×96 (top row four ColorChecker
spectra, bottom row metamers of them: same CIE 1931 XYZ under D65), reconstructed with
the sensor's per-pixel thresholds and with nominal ones. A pixel is "told apart" when
its reconstruction is closer (spectral angle) to its own true spectrum than to its
twin's. Also reported: the sRGB difference of each pair's truths (≈ 0) and the mean
SAM between the reconstructed twins against the true twins' SAM.

Run: `.venv/bin/python experiments/metamers.py` (about 1 min on 2 cores).
"""

import numpy as np
from _common import capture, pyplot, save, timed_reconstruct

import evhsi_jax as ev


def main():
    rig, scene, events, info, truth = capture("metamers", (48, 96))
    out = {}
    for mode in ("per-pixel", "nominal"):
        cube, _ = timed_reconstruct(events, rig, info if mode == "per-pixel" else None)
        m = ev.evaluate(cube, truth)
        pairs = []
        for k in range(4):
            a_sel, b_sel = scene.labels == k, scene.labels == k + 4
            ta, tb = truth[a_sel][0], truth[b_sel][0]
            ra, rb = cube[a_sel], cube[b_sel]
            own_a = ev.metrics.sam_map_deg(ra, np.broadcast_to(ta, ra.shape))
            twin_a = ev.metrics.sam_map_deg(ra, np.broadcast_to(tb, ra.shape))
            own_b = ev.metrics.sam_map_deg(rb, np.broadcast_to(tb, rb.shape))
            twin_b = ev.metrics.sam_map_deg(rb, np.broadcast_to(ta, rb.shape))
            told = float(np.mean(np.concatenate([own_a < twin_a, own_b < twin_b])))
            srgb = ev.cube_to_srgb(np.stack([ta, tb])[None], rig.wavelengths_nm)[0]
            pairs.append(
                {
                    "pair": scene.names[k],
                    "told_apart_fraction": told,
                    "true_twin_sam_deg": float(ev.metrics.sam_map_deg(ta, tb)),
                    "recon_twin_sam_deg": float(ev.metrics.sam_map_deg(ra.mean(0), rb.mean(0))),
                    "truth_srgb_max_diff_8bit": float(
                        255 * np.abs(srgb[0] - srgb[1]).max()
                    ),
                }
            )
            print(
                f"{mode:9s} {scene.names[k]:20s} told apart {told:6.1%}  twin SAM true "
                f"{pairs[-1]['true_twin_sam_deg']:.1f}° recon "
                f"{pairs[-1]['recon_twin_sam_deg']:.1f}°  sRGB Δ "
                f"{pairs[-1]['truth_srgb_max_diff_8bit']:.2f}/255",
                flush=True,
            )
        out[mode] = {"metrics": m, "pairs": pairs}
        print(
            f"{mode}: SAM {m['sam_deg']:.2f} PSNR {m['psnr_db']:.2f} (paper Fig. 7: "
            "10.8°, 34.95 dB)"
        )
        if mode == "per-pixel":
            keep = cube
    plt = pyplot()
    fig, axes = plt.subplots(1, 5, figsize=(16, 3))
    axes[0].imshow(ev.cube_to_srgb(keep, rig.wavelengths_nm))
    axes[0].set_title("reconstruction (sRGB)")
    axes[0].axis("off")
    for k, ax in enumerate(axes[1:]):
        for lab, col in ((k, "C0"), (k + 4, "C3")):
            sel = scene.labels == lab
            ax.plot(rig.wavelengths_nm, truth[sel][0], col + "--", lw=1)
            ax.plot(rig.wavelengths_nm, keep[sel].mean(0), col, lw=1)
        ax.set_title(scene.names[k], fontsize=8)
    fig.tight_layout()
    save("metamers", {"setup": __doc__, "results": out}, fig)


if __name__ == "__main__":
    main()
