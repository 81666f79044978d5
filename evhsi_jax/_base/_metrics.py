"""Spectral image quality metrics (the definitions of DESIGN.md, NumPy).

- **SAM** (degrees): per pixel the angle $\\arccos\\frac{\\hat s\\cdot s}{\\|\\hat s\\|\\|s\\|}$
  between the estimated and the true spectrum, averaged over pixels. A pixel where either
  spectrum is all zero has no angle; it counts as 90° if only one is zero and 0° if both
  are (so a black estimate of a non-black pixel is maximally wrong, not ignored).
- **MSE** over the whole cube; **RMS** $=\\sqrt{\\mathrm{MSE}}$;
  **PSNR** $=10\\log_{10}(\\mathrm{peak}^2/\\mathrm{MSE})$ dB with peak = 1 (reflectance).
- **SSIM**: the structural similarity of each channel image (Gaussian window σ = 1.5,
  $K_1 = 0.01$, $K_2 = 0.03$, data range 1, as Wang et al. 2004), averaged over channels.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sam_deg", "psnr_db", "rms", "ssim", "evaluate", "per_label_table"]


def _pair(est, ref):
    est = np.asarray(est, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if est.shape != ref.shape:
        raise ValueError(f"cube shapes differ: estimate {est.shape}, truth {ref.shape}")
    if not np.all(np.isfinite(est)) or not np.all(np.isfinite(ref)):
        raise ValueError("cubes must be finite")
    return est, ref


def sam_map_deg(est, ref) -> np.ndarray:
    """Per-pixel spectral angle in degrees, shape `est.shape[:-1]`."""
    est, ref = _pair(est, ref)
    dot = np.sum(est * ref, axis=-1)
    ne = np.linalg.norm(est, axis=-1)
    nr = np.linalg.norm(ref, axis=-1)
    both = (ne > 0) & (nr > 0)
    cos = np.where(both, dot / np.where(both, ne * nr, 1.0), 0.0)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return np.where(both, ang, np.where((ne == 0) & (nr == 0), 0.0, 90.0))


def sam_deg(est, ref) -> float:
    """Mean spectral angle over pixels, degrees."""
    return float(np.mean(sam_map_deg(est, ref)))


def mse(est, ref) -> float:
    est, ref = _pair(est, ref)
    return float(np.mean((est - ref) ** 2))


def rms(est, ref) -> float:
    """Root mean squared error over the whole cube (reflectance units)."""
    return float(np.sqrt(mse(est, ref)))


def psnr_db(est, ref, peak: float = 1.0) -> float:
    """$10 \\log_{10}(\\mathrm{peak}^2 / \\mathrm{MSE})$; +inf for identical cubes."""
    e = mse(est, ref)
    return float("inf") if e == 0 else float(10.0 * np.log10(peak**2 / e))


def _ssim_2d(a, b, data_range=1.0, sigma=1.5):
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    # Gaussian window truncated at 3.5σ (11×11 for σ = 1.5), edges reflected.
    from scipy import ndimage  # here: its import costs ~0.2 s of every start

    filt = lambda img: ndimage.gaussian_filter(img, sigma, truncate=3.5, mode="reflect")  # noqa: E731
    mu_a, mu_b = filt(a), filt(b)
    saa = filt(a * a) - mu_a**2
    sbb = filt(b * b) - mu_b**2
    sab = filt(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * sab + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2)
    return float(np.mean(num / den))


def ssim(est, ref, data_range: float = 1.0) -> float:
    """Mean over channels of the SSIM of each `(H, W)` channel image."""
    est, ref = _pair(est, ref)
    if est.ndim != 3:
        raise ValueError(f"SSIM needs (H, W, M) cubes, got {est.shape}")
    return float(
        np.mean(
            [
                _ssim_2d(est[..., i], ref[..., i], data_range)
                for i in range(est.shape[-1])
            ]
        )
    )


def evaluate(est, ref) -> dict:
    """All metrics of the contract: `sam_deg`, `psnr_db`, `ssim`, `rms`."""
    return {
        "sam_deg": sam_deg(est, ref),
        "psnr_db": psnr_db(est, ref),
        "ssim": ssim(est, ref),
        "rms": rms(est, ref),
    }


def per_label_table(est, ref, labels, names=()) -> list[dict]:
    """SAM, RMS and PSNR per label (e.g. per ColorChecker patch), over its pixels."""
    est, ref = _pair(est, ref)
    labels = np.asarray(labels)
    rows = []
    for lab in np.unique(labels):
        sel = labels == lab
        e, r = est[sel], ref[sel]
        err = float(np.mean((e - r) ** 2))
        rows.append(
            {
                "label": int(lab),
                "name": str(names[lab]) if lab < len(names) else str(lab),
                "pixels": int(sel.sum()),
                "sam_deg": float(np.mean(sam_map_deg(e, r))),
                "rms": float(np.sqrt(err)),
                "psnr_db": float("inf") if err == 0 else float(-10 * np.log10(err)),
            }
        )
    return rows
