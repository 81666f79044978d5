"""`evhsi view`: a local web page to look at a cube or a per-sweep video.

The server binds to 127.0.0.1 only (from another machine: an SSH tunnel, `ssh -L
PORT:127.0.0.1:PORT HOST`, then open http://127.0.0.1:PORT here) and serves one
self-contained page (no script or font from elsewhere: it works offline) plus a small
JSON/PNG API it reads:

- `GET /api/meta`: `{kind, height, width, wavelengths_nm, sweeps, has_truth, source}`
  (`sweeps`: the index entries of a per-sweep folder or store; one for a cube).
- `GET /api/image.png?sweep=I&channel=C`: the sRGB rendering (`channel=-1`) or one
  channel as a gray image scaled to [0, 1] reflectance, of sweep position `I`.
- `GET /api/spectrum?x=X&y=Y&sweep=I`: `{spectrum, truth, sam_deg}` of that pixel
  (`truth` and `sam_deg` null without `--truth`).

The page shows the image (click a pixel: its spectrum is plotted, several pixels are
kept for comparison, each in its own colour; the truth dashed, with SAM), a wavelength
slider for single channels, and for a video a sweep slider with play/pause that
follows the newest sweep when asked (what a live `reconstruct --per-sweep --follow`
run writes).
"""

from __future__ import annotations

import io
import json
import math
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np

from .._io import cube_to_srgb, load_cube

__all__ = ["CubeSource", "make_server", "PAGE"]


class CubeSource:
    """What the viewer shows: one cube file, or a per-sweep folder / video store
    (re-read on each request for the sweep list, so a growing run shows up)."""

    def __init__(self, path, truth=None):
        from ._store import holds_video
        from ._stream import load_sweep_index

        self.path = Path(path)
        self.truth = None
        if (self.path / "index.json").is_file() or holds_video(self.path):
            self.kind = "sweeps"
            index = load_sweep_index(self.path)
            self.height, self.width = int(index["height"]), int(index["width"])
            self.wl = np.asarray(index["wavelengths_nm"], np.float64)
        else:
            self.kind = "cube"
            data = load_cube(self.path)
            self._cube = data["cube"]
            self.height, self.width = self._cube.shape[:2]
            self.wl = np.asarray(data["wavelengths_nm"], np.float64)
        if truth is not None:
            t = load_cube(truth)
            if t["cube"].shape != (self.height, self.width, self.wl.size):
                raise ValueError(
                    f"--truth {truth} is {t['cube'].shape}, the cube "
                    f"{(self.height, self.width, self.wl.size)}"
                )
            self.truth = t["cube"]
        self._lock = threading.Lock()
        self._cached: tuple[int, np.ndarray] | None = None

    def entries(self) -> list[dict]:
        if self.kind == "cube":
            return [{"sweep": 0, "position": 0}]
        from ._stream import load_sweep_index

        return load_sweep_index(self.path)["sweeps"]

    def cube(self, i: int) -> np.ndarray:
        """The cube of sweep position `i` (the last one read is kept)."""
        if self.kind == "cube":
            return self._cube
        with self._lock:
            if self._cached is not None and self._cached[0] == i:
                return self._cached[1]
            entries = self.entries()
            if not 0 <= i < len(entries):
                raise ValueError(f"no sweep at position {i} (have {len(entries)})")
            entry = entries[i]
            if entry.get("file"):
                cube = load_cube(self.path / entry["file"])["cube"]
            else:
                from ._store import VideoStore

                cube = VideoStore(self.path, "r").cube_file(entry["position"])["cube"]
            self._cached = (i, cube)
            return cube

    def meta(self) -> dict:
        return {
            "kind": self.kind,
            "source": self.path.name,
            "height": self.height,
            "width": self.width,
            "wavelengths_nm": [float(v) for v in self.wl],
            "sweeps": self.entries(),
            "has_truth": self.truth is not None,
        }

    def image_png(self, i: int, channel: int) -> bytes:
        from PIL import Image

        cube = np.nan_to_num(self.cube(i), nan=0.0, posinf=0.0, neginf=0.0)
        if channel < 0:
            img = np.round(255 * cube_to_srgb(cube, self.wl)).astype(np.uint8)
        else:
            if not 0 <= channel < self.wl.size:
                raise ValueError(f"channel must be in [0, {self.wl.size})")
            img = np.round(255 * np.clip(cube[..., channel], 0, 1)).astype(np.uint8)
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="PNG")
        return buf.getvalue()

    def spectrum(self, i: int, x: int, y: int) -> dict:
        if not (0 <= x < self.width and 0 <= y < self.height):
            raise ValueError(f"pixel ({x}, {y}) is outside {self.width}x{self.height}")
        s = self.cube(i)[y, x].astype(np.float64)
        out = {"x": x, "y": y, "sweep": i, "spectrum": _finite_list(s), "truth": None,
               "sam_deg": None}  # fmt: skip
        if self.truth is not None:
            t = self.truth[y, x].astype(np.float64)
            out["truth"] = _finite_list(t)
            den = np.linalg.norm(s) * np.linalg.norm(t)
            if den > 0 and np.all(np.isfinite(s)):
                cos = float(np.clip(s @ t / den, -1.0, 1.0))
                out["sam_deg"] = math.degrees(math.acos(cos))
        return out


def _finite_list(a) -> list:
    return [float(v) if np.isfinite(v) else None for v in a]


def make_server(source: CubeSource, port: int = 0) -> ThreadingHTTPServer:
    """An HTTP server for `source` on 127.0.0.1:`port` (0: a free port); call
    `serve_forever()` on it. Only 127.0.0.1 is ever bound."""

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args):  # quiet: the terminal shows the URL only
            pass

        def _send(self, code, body: bytes, ctype: str):
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):  # noqa: N802 (the http.server API)
            url = urlparse(self.path)
            q = {k: v[-1] for k, v in parse_qs(url.query).items()}
            try:
                if url.path in ("/", "/index.html"):
                    self._send(200, PAGE.encode(), "text/html; charset=utf-8")
                elif url.path == "/api/meta":
                    self._send(200, json.dumps(source.meta()).encode(), "application/json")
                elif url.path == "/api/image.png":
                    png = source.image_png(int(q.get("sweep", 0)), int(q.get("channel", -1)))
                    self._send(200, png, "image/png")
                elif url.path == "/api/spectrum":
                    spec = source.spectrum(int(q.get("sweep", 0)), int(q["x"]), int(q["y"]))
                    self._send(200, json.dumps(spec).encode(), "application/json")
                else:
                    self._send(404, b"not found", "text/plain")
            except (ValueError, KeyError) as err:
                msg = json.dumps({"error": " ".join(str(err).split())}).encode()
                self._send(400, msg, "application/json")

    return ThreadingHTTPServer(("127.0.0.1", int(port)), Handler)


PAGE = (Path(__file__).with_name("viewer.html")).read_text(encoding="utf-8")
