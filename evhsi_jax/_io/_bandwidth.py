"""Bandwidth accounting: bytes of an event stream versus frames.

Three measures, for the paper's bandwidth comparison (DESIGN.md counts events at 16
bits):

- `evt3_bytes`: the exact size of the EVT 3.0 encoding our writer produces (time, row
  and vector words included). It comes from the writer's own word plan, so it always
  equals the payload of the file `write_evt3` writes (plus the header when asked).
- `nominal_event_bytes`: the paper's accounting, a fixed number of bits per event.
- `frame_bytes`: `frames × width × height` pixels at 8 bits (or `bits_per_pixel`).

How the two event measures compare depends on the event layout: EVT 3.0 pays one word
per event only when events share a row and µs; events that share a µs and a row cost
about a word per 12 columns (vector words), but a column sweep (events along a column,
each in a new row) costs a row word per event, and events that each have their own µs
add a TIME_LOW word each — up to 48 bits per event.
"""

from __future__ import annotations

import numpy as np

from .._model import EventStream
from ._evt3_encode import evt3_word_count
from ._header import format_header

__all__ = ["evt3_bytes", "nominal_event_bytes", "frame_bytes", "bandwidth_summary"]


def evt3_bytes(
    events: EventStream, *, reorder: bool = False, header: bool = False
) -> int:
    """Bytes of the EVT 3.0 encoding of `events` (what `write_evt3` writes).

    **Arguments:**

    - `events`: the stream.
    - `reorder`: as for `write_evt3` (sort each µs by row, polarity, column first).
    - `header`: include the text header our writer puts first.

    **Returns:** the byte count.
    """
    n = 2 * evt3_word_count(events, reorder=reorder)
    if header:
        n += len(format_header("evt3", events.width, events.height))
    return n


def nominal_event_bytes(
    n_events: int | np.integer, bits_per_event: int | np.integer = 16
) -> float:
    """The paper's event accounting: `n_events × bits_per_event / 8` bytes.

    **Arguments:**

    - `n_events`: number of events.
    - `bits_per_event`: bits counted per event (16 for EVT 3.0 in the paper).

    **Returns:** bytes (a float, since bits need not fill whole bytes).
    """
    if n_events < 0 or bits_per_event <= 0:
        raise ValueError("n_events must be >= 0 and bits_per_event > 0")
    return int(n_events) * int(bits_per_event) / 8


def frame_bytes(
    frames: int | np.integer,
    width: int | np.integer,
    height: int | np.integer,
    bits_per_pixel: int | np.integer = 8,
) -> float:
    """Bytes of `frames` monochrome frames of `width × height` pixels.

    **Arguments:**

    - `frames`: number of frames (e.g. channels × sweeps for a frame-camera scan).
    - `width`, `height`: frame size in pixels.
    - `bits_per_pixel`: 8 in the paper.

    **Returns:** bytes (`frames · width · height · bits_per_pixel / 8`).
    """
    if frames < 0 or width <= 0 or height <= 0 or bits_per_pixel <= 0:
        raise ValueError("frames must be >= 0 and width, height, bits_per_pixel > 0")
    return int(frames) * int(width) * int(height) * int(bits_per_pixel) / 8


def bandwidth_summary(
    events: EventStream, *, frames: int | None = None, bits_per_pixel: int = 8
) -> dict:
    """All measures side by side for one stream.

    **Arguments:**

    - `events`: the stream.
    - `frames`: the number of frames to compare with (omit to skip the frame columns).
    - `bits_per_pixel`: frame bit depth.

    **Returns:** a JSON-ready dict: `events`, `evt3_bytes` (as ordered),
    `evt3_bytes_reordered`, `evt3_bits_per_event`, `nominal16_bytes`, and with `frames`:
    `frame_bytes`, `evt3_over_frames`, `nominal16_over_frames`.
    """
    n = len(events)
    actual = evt3_bytes(events)
    out = {
        "events": n,
        "evt3_bytes": actual,
        "evt3_bytes_reordered": evt3_bytes(events, reorder=True),
        "evt3_bits_per_event": (8 * actual / n) if n else None,
        "nominal16_bytes": nominal_event_bytes(n, 16),
    }
    if frames is not None:
        fb = frame_bytes(frames, events.width, events.height, bits_per_pixel)
        out.update(
            frame_bytes=fb,
            evt3_over_frames=actual / fb if fb else None,
            nominal16_over_frames=out["nominal16_bytes"] / fb if fb else None,
        )
    return out
