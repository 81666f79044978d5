"""What a decoder met on its way through a file: the record behind the lenient policy.

Readers are *lenient* by default: local defects (unknown word types, events outside the
geometry, events before the first time or row word, a trailing partial word) are skipped
and counted here, and decoding goes on. With `strict=True` the first such defect raises
a `ValueError` that names it and its byte offset. Real-sensor quirks that are not
defects (TIME_LOW stepping back within one TIME_HIGH, small TIME_HIGH glitches) are
counted too, but never raise: see `time_clamped`.
"""

from __future__ import annotations

import dataclasses

__all__ = ["DecodeReport", "DecodeError", "QUIRK_STEP_US"]

# The largest step back a working sensor produces: EVT 3.0's TIME_LOW spans 4096 µs
# under one TIME_HIGH (EVT 2.0's 64 µs). Anything larger is time jumping back.
QUIRK_STEP_US = 4096


class DecodeError(ValueError):
    """A defect met while decoding with `strict=True` (a `ValueError`)."""


@dataclasses.dataclass
class DecodeReport:
    """Counters filled while decoding one file (mutable, updated chunk by chunk).

    **Arguments:** (all counts)

    - `words`: data words read (16-bit for EVT 3.0, 32-bit for EVT 2.0).
    - `events`, `triggers`: CD events and external trigger events produced.
    - `time_wraps`: wrap-arounds of the stream's time base that were extended away.
    - `time_glitches`: TIME_HIGH values that stepped back by less than half the range
      (a sensor glitch, not a wrap; time is held by the running maximum).
    - `time_clamped`: events (and triggers) whose decoded time was below an earlier one
      and was raised to it (TIME_LOW step-backs); `max_step_back_us` is the largest such
      step.
    - `other_words`: OTHERS / CONTINUED words (valid, carry no CD events; skipped).
    - `system_type_rows`: EVT_ADDR_Y words with the system-type (slave) bit set.
    - Defects (skipped in lenient mode, `ValueError` in strict mode):
      `unknown_words` (reserved word types), `out_of_geometry` (events outside
      width x height), `events_before_time` (events/triggers before the first
      TIME_HIGH), `events_without_row` (events before the first EVT_ADDR_Y, or vector
      words before the first VECT_BASE_X), `trailing_bytes` (a partial word at the end).
    """

    words: int = 0
    events: int = 0
    triggers: int = 0
    time_wraps: int = 0
    time_glitches: int = 0
    time_clamped: int = 0
    max_step_back_us: int = 0
    other_words: int = 0
    system_type_rows: int = 0
    unknown_words: int = 0
    out_of_geometry: int = 0
    events_before_time: int = 0
    events_without_row: int = 0
    trailing_bytes: int = 0

    DEFECTS = (
        "unknown_words",
        "out_of_geometry",
        "events_before_time",
        "events_without_row",
        "trailing_bytes",
    )

    @property
    def defects(self) -> int:
        """The number of skipped defects of all kinds."""
        return sum(getattr(self, k) for k in self.DEFECTS)

    @property
    def clean(self) -> bool:
        """True when nothing was skipped."""
        return self.defects == 0

    def summary(self) -> str:
        """One line for a user: what was decoded and, if anything, what was skipped."""
        text = f"{self.events} events, {self.triggers} triggers from {self.words} words"
        skipped = [f"{getattr(self, k)} {k}" for k in self.DEFECTS if getattr(self, k)]
        if skipped:
            text += "; skipped " + ", ".join(skipped)
        if self.time_clamped:
            text += (
                f"; {self.time_clamped} timestamps held at the running maximum "
                f"(largest step back {self.max_step_back_us} us)"
            )
        return text

    def problems(self) -> list[str]:
        """What a user must hear about, one phrase each (empty for a clean file):
        skipped defects, and timestamps that went back. Small step-backs (below
        `QUIRK_STEP_US`) are a sensor quirk and stay silent; a larger one means time
        jumped back (a concatenated or damaged file) and is listed."""
        out = [f"{getattr(self, k)} {k.replace('_', ' ')} skipped" for k in self.DEFECTS
               if getattr(self, k)]  # fmt: skip
        if self.time_jumped_back:
            out.append(
                f"time jumps back by up to {self.max_step_back_us} µs ("
                f"{self.time_clamped} timestamps held at the running maximum; a "
                "concatenated or damaged recording?)"
            )
        return out

    @property
    def time_jumped_back(self) -> bool:
        """True when some timestamp stepped back by more than a sensor quirk can."""
        return self.time_clamped > 0 and self.max_step_back_us > QUIRK_STEP_US

    def as_dict(self) -> dict:
        """The counters as a plain dict (JSON-ready)."""
        return dataclasses.asdict(self)
