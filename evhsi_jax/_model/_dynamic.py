"""Dynamic scenes: one :class:`Scene` per sweep, for video-rate simulation.

:func:`evhsi_jax.simulate` takes a list of per-sweep scenes; these builders make such
lists from the built-in charts, with the per-sweep truth available as
`scenes[k].truth_cube(rig.grid)` (:func:`truth_cubes`).

- `"translate"`: the ColorChecker (or any built-in chart) gliding back and forth over a
  gray background;
- `"rotate"`: the chart turning about its centre;
- `"iridescent"`: a static chart beside a disc whose reflectance peak moves with the
  viewing angle, like a thin film: $λ_{peak}(θ) = λ_0 \\sqrt{1 - \\sin^2 θ / n^2}$,
  θ rocking between 0 and `max_angle_deg` — the spectrum changes while the geometry
  does not;
- `"mixed"`: all three at once.

**Approximation.** The simulator holds each sweep's scene still for the whole sweep and
switches at the sweep boundary; a real moving scene also moves *during* a sweep (at
0.5 px/sweep, a pixel on an edge sees its material change somewhere inside the sweep,
and its events mix two spectra). Motion here is sampled at the sweep rate, placed with
nearest-neighbour sampling (edges move by whole pixels, no mixed pixels), and every
per-sweep scene shares one palette (same size, so one compilation serves them all).
"""

from __future__ import annotations

import math

import numpy as np

from ._scenes import Scene, load_scene

__all__ = [
    "DYNAMIC_SCENES",
    "dynamic_scene",
    "moving_chart",
    "iridescent_reflectance",
    "truth_cubes",
    "changed_pixels",
]

DYNAMIC_SCENES = ("translate", "rotate", "iridescent", "mixed")
BACKGROUND = "neutral 5 (.70 D)"  # a mid gray from the ColorChecker


def iridescent_reflectance(
    wavelengths_nm,
    angle_deg: float,
    *,
    peak_nm: float = 680.0,
    index: float = 1.4,
    width_nm: float = 25.0,
    floor: float = 0.05,
    height: float = 0.85,
) -> np.ndarray:
    """A thin-film-like reflectance at viewing angle θ: a Gaussian peak at
    $λ_0 \\sqrt{1 - \\sin^2θ / n^2}$ on a flat floor.

    **Arguments:**

    - `wavelengths_nm`: sample wavelengths `(L,)`.
    - `angle_deg`: viewing angle θ in degrees (0: normal incidence, peak at `peak_nm`).
    - `peak_nm`, `index`: λ₀ and the film's refractive index n.
    - `width_nm`: the peak's standard deviation; `floor`, `height`: reflectance off
      and on the peak.

    **Returns:** reflectance `(L,)` in [0, 1].
    """
    wl = np.asarray(wavelengths_nm, np.float64)
    s = math.sin(math.radians(angle_deg)) / index
    centre = peak_nm * math.sqrt(max(1.0 - s * s, 0.0))
    return floor + height * np.exp(-0.5 * ((wl - centre) / width_nm) ** 2)


def _ping_pong(x: float) -> float:
    """A triangle wave: 0 → 1 → 0 as x goes 0 → 1 → 2."""
    x = x % 2.0
    return x if x <= 1.0 else 2.0 - x


def moving_chart(
    size: tuple[int, int] = (48, 64),
    sweeps: int = 30,
    *,
    chart: str = "colorchecker",
    chart_height: int | None = None,
    velocity_px_per_sweep: float = 0.5,
    deg_per_sweep: float = 0.0,
    iridescent: bool = False,
    max_angle_deg: float = 60.0,
    rock_sweeps: int = 60,
    background: str = BACKGROUND,
) -> list[Scene]:
    """A chart moving over a gray background, one :class:`Scene` per sweep.

    **Arguments:**

    - `size`: `(H, W)` of the image; `sweeps`: number of scenes.
    - `chart`: a built-in scene (`colorchecker`, `metamers`, `tcs`, …) drawn as the
      moving object; `chart_height`: its height in pixels (default 60 % of H, width by
      its own aspect ratio).
    - `velocity_px_per_sweep`: horizontal speed; the chart glides back and forth
      between the image edges (a triangle wave).
    - `deg_per_sweep`: rotation speed about the chart's centre.
    - `iridescent`: add a disc in the top-right corner whose reflectance follows
      :func:`iridescent_reflectance` with θ rocking 0 → `max_angle_deg` → 0 every
      `rock_sweeps` sweeps.
    - `background`: name of the ColorChecker patch behind the chart.

    **Returns:** a list of `sweeps` scenes of one size and one palette size.
    """
    h, w = size
    if sweeps < 1:
        raise ValueError(f"sweeps must be >= 1, got {sweeps}")
    if h < 4 or w < 4:
        raise ValueError(f"size must be at least 4x4, got {h}x{w}")
    ref = load_scene("colorchecker", (4, 6))
    if background not in ref.names:
        raise ValueError(f"unknown background patch {background!r}")
    ch = chart_height or max(2, round(0.6 * h))
    base = load_scene(chart, (8, 8))  # its native layout, for the aspect ratio
    rows, cols = _layout(base)
    cw = min(w, max(2, round(ch * cols / rows)))
    ch = min(h, ch)
    art = load_scene(chart, (ch, cw))
    wl = np.asarray(art.wavelengths_nm, np.float64)
    bg = np.interp(wl, ref.wavelengths_nm, ref.palette[ref.names.index(background)])
    palette = [art.palette, bg[None, :]]
    bg_label = art.palette.shape[0]
    names = [*art.names, f"background ({background})"]
    if iridescent:
        palette.append(iridescent_reflectance(wl, 0.0)[None, :])
        names.append("iridescent")
    palette = np.concatenate(palette)

    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    radius = 0.18 * min(h, w)
    disc = (yy - (radius + 1)) ** 2 + (xx - (w - radius - 1)) ** 2 <= radius**2
    travel = max(w - cw, 0)
    scenes = []
    for k in range(sweeps):
        cx = 0.5 * cw + travel * (
            _ping_pong(k * velocity_px_per_sweep / travel) if travel else 0.0
        )
        cy = 0.5 * h
        a = math.radians(k * deg_per_sweep)
        # Inverse map: image pixel → chart coordinates (rotation about the centre).
        u = math.cos(a) * (xx - cx) + math.sin(a) * (yy - cy) + 0.5 * cw
        v = -math.sin(a) * (xx - cx) + math.cos(a) * (yy - cy) + 0.5 * ch
        inside = (u >= 0) & (u < cw) & (v >= 0) & (v < ch)
        ui = np.clip(u.astype(np.int64), 0, cw - 1)
        vi = np.clip(v.astype(np.int64), 0, ch - 1)
        labels = np.where(inside, art.labels[vi, ui], bg_label)
        pal = palette
        if iridescent:
            theta = (
                max_angle_deg * 0.5 * (1.0 - math.cos(2 * math.pi * k / rock_sweeps))
            )
            pal = palette.copy()
            pal[-1] = iridescent_reflectance(wl, theta)
            labels = np.where(disc, palette.shape[0] - 1, labels)
        scenes.append(Scene(pal, wl, labels, names))
    return scenes


def _layout(scene: Scene) -> tuple[int, int]:
    """Rows and columns of a chart's patch grid (from its label image)."""
    lab = scene.labels
    rows = len(np.unique(lab[:, 0]))
    cols = len(np.unique(lab[0, :]))
    return max(rows, 1), max(cols, 1)


def dynamic_scene(
    name: str, size: tuple[int, int] | None = None, sweeps: int = 30, **kwargs
) -> list[Scene]:
    """A named dynamic scene (`DYNAMIC_SCENES`), one :class:`Scene` per sweep.

    - `"translate"`: ColorChecker gliding at 0.5 px/sweep;
    - `"rotate"`: ColorChecker turning at 2°/sweep, not translating;
    - `"iridescent"`: static ColorChecker and an iridescent disc (θ 0–60° per 60
      sweeps);
    - `"mixed"`: gliding and turning at once, with the iridescent disc.

    Keyword arguments override :func:`moving_chart`'s. Default size 48×64.
    """
    presets = {
        "translate": dict(velocity_px_per_sweep=0.5),
        "rotate": dict(velocity_px_per_sweep=0.0, deg_per_sweep=2.0),
        "iridescent": dict(velocity_px_per_sweep=0.0, iridescent=True),
        "mixed": dict(velocity_px_per_sweep=0.5, deg_per_sweep=1.0, iridescent=True),
    }
    if name not in presets:
        raise ValueError(
            f"unknown dynamic scene {name!r}; choose from {', '.join(DYNAMIC_SCENES)}"
        )
    return moving_chart(size or (48, 64), sweeps, **{**presets[name], **kwargs})


def truth_cubes(scenes: list[Scene], grid) -> np.ndarray:
    """Per-sweep truth on the channel grid, `(sweeps, H, W, M)` float32 (for long
    recordings, call `scene.truth_cube(grid)` per sweep instead)."""
    return np.stack([s.truth_cube(grid) for s in scenes])


def changed_pixels(scenes: list[Scene], grid) -> np.ndarray:
    """Per sweep, the pixels whose channel spectrum differs from the previous sweep's,
    `(sweeps, H, W)` bool (all False for sweep 0): where motion or iridescence makes
    the carried reference an approximation."""
    out = np.zeros((len(scenes), scenes[0].height, scenes[0].width), bool)
    prev = scenes[0].truth_cube(grid)
    for k in range(1, len(scenes)):
        cur = scenes[k].truth_cube(grid)
        out[k] = np.any(np.abs(cur - prev) > 1e-6, axis=-1)
        prev = cur
    return out
