"""The text header of Prophesee `.raw` files: `% key value` lines before the binary
words.

A header is a run of lines that start with `%`, optionally closed by `% end`. Older
recordings (such as the bundled `evt3_sample.raw`) have no `% end` line: the header then
stops at the first line that does not start with `%`, or at the first "line" that is not
text (a data word whose low byte happens to be `%` is binary, not a header line).

Geometry comes, in order of preference, from `% geometry WxH`, from the
`width=`/`height=` fields of `% format EVT3;height=H;width=W`, or from `% width W` / `%
height H` lines; if none is present the reader falls back to the 1280x720 sensor of
DESIGN.md. Conflicting geometry or format lines are a `ValueError` (the file is
ambiguous, not just damaged).
"""

from __future__ import annotations

import dataclasses
import re

__all__ = ["RawHeader", "parse_header", "format_header", "DEFAULT_GEOMETRY"]

DEFAULT_GEOMETRY = (1280, 720)
# The longest header we are willing to scan, and the longest single line: a real header
# is well under a kilobyte; a file that is all "%" is not an event file.
MAX_HEADER_BYTES = 1 << 20
MAX_LINE_BYTES = 1 << 16

_FORMAT_NAMES = {
    "evt3": "evt3",
    "evt3.0": "evt3",
    "evt2": "evt2",
    "evt2.0": "evt2",
    "evt21": "evt21",
    "evt2.1": "evt21",
}


@dataclasses.dataclass(frozen=True)
class RawHeader:
    """The parsed header of a Prophesee `.raw` file.

    **Arguments:**

    - `fields`: the `(key, value)` pairs in file order (keys as written).
    - `size`: bytes taken by the header, i.e. the offset of the first data word.
    - `format`: `"evt3"`, `"evt2"`, `"evt21"` or `None` when the header does not say.
    - `width`, `height`: geometry stated by the header, or `None`.
    - `has_end`: whether the header was closed by a `% end` line.
    """

    fields: tuple[tuple[str, str], ...]
    size: int
    format: str | None
    width: int | None
    height: int | None
    has_end: bool

    def get(self, key: str) -> str | None:
        """The value of the first field named `key` (case-insensitive), or `None`."""
        key = key.lower()
        for k, v in self.fields:
            if k.lower() == key:
                return v
        return None

    def geometry(self, default: tuple[int, int] = DEFAULT_GEOMETRY) -> tuple[int, int]:
        """`(width, height)` from the header, else `default`."""
        if self.width is None or self.height is None:
            return default
        return self.width, self.height


def _as_text_line(raw: bytes) -> str | None:
    """Decode one candidate header line, or `None` if it is binary data."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return None
    if any(ord(c) < 32 and c not in "\t\r" for c in text) or "\x7f" in text:
        return None
    return text.rstrip("\r")


def _positive_int(value: str, what: str) -> int:
    try:
        n = int(value)
    except ValueError:
        raise ValueError(f"header {what} {value!r} is not an integer") from None
    if n <= 0 or n > 1 << 16:
        raise ValueError(f"header {what} {n} is outside 1..65536")
    return n


def _merge(found: dict, key: str, value, source: str) -> None:
    if key in found and found[key][0] != value:
        raise ValueError(
            f"header is ambiguous: {found[key][1]} says {key}={found[key][0]}, "
            f"{source} says {key}={value}"
        )
    found.setdefault(key, (value, source))


def parse_header(data: bytes, *, at_eof: bool = True) -> RawHeader:
    """Parse the header at the start of `data` (the first bytes of a `.raw` file).

    **Arguments:**

    - `data`: the file's first bytes; at least the whole header (up to 1 MiB is read).
    - `at_eof`: whether `data` is the whole file (then a last line without a newline
      still counts as a header line).

    **Returns:** a `RawHeader`; `size` is 0 when the file has no header at all.

    Raises `ValueError` for an over-long header, unparsable geometry, or header lines
    that contradict each other.
    """
    pos = 0
    fields: list[tuple[str, str]] = []
    has_end = False
    while pos < len(data) and data[pos : pos + 1] == b"%":
        nl = data.find(b"\n", pos, pos + MAX_LINE_BYTES)
        if nl < 0:
            if len(data) - pos >= MAX_LINE_BYTES:
                text = _as_text_line(data[pos : pos + 256])
                if text is None:
                    break  # binary data that starts with '%': header is over
                raise ValueError(
                    f"header line at byte {pos} is longer than {MAX_LINE_BYTES} bytes"
                )
            if not at_eof:
                raise ValueError(f"header line at byte {pos} is not terminated")
            nl = len(data)
        text = _as_text_line(data[pos + 1 : nl])
        if text is None:
            break
        pos = min(nl + 1, len(data))
        if pos > MAX_HEADER_BYTES:
            raise ValueError(f"header is longer than {MAX_HEADER_BYTES} bytes")
        body = text.strip()
        if body.lower() == "end":
            has_end = True
            break
        if not body:
            continue
        key, _, value = body.partition(" ")
        fields.append((key, value.strip()))

    found: dict[str, tuple] = {}
    for key, value in fields:
        k = key.lower()
        if k == "evt":
            name = _FORMAT_NAMES.get("evt" + value.strip().lower())
            if name is None:
                raise ValueError(f"header names an unknown event format 'evt {value}'")
            _merge(found, "format", name, f"'% evt {value}'")
        elif k == "format":
            parts = [s.strip() for s in value.split(";")]
            name = _FORMAT_NAMES.get(parts[0].lower())
            if name is None:
                raise ValueError(f"header names an unknown event format {parts[0]!r}")
            _merge(found, "format", name, f"'% format {value}'")
            for part in parts[1:]:
                pk, _, pv = part.partition("=")
                if pk.strip().lower() in ("width", "height"):
                    n = _positive_int(pv.strip(), pk.strip().lower())
                    _merge(found, pk.strip().lower(), n, "'% format'")
        elif k == "geometry":
            m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", value)
            if m is None:
                raise ValueError(f"header geometry {value!r} is not WIDTHxHEIGHT")
            _merge(found, "width", _positive_int(m[1], "width"), "'% geometry'")
            _merge(found, "height", _positive_int(m[2], "height"), "'% geometry'")
        elif k in ("width", "height"):
            _merge(found, k, _positive_int(value, k), f"'% {key}'")
    width = found.get("width", (None,))[0]
    height = found.get("height", (None,))[0]
    if (width is None) != (height is None):
        raise ValueError("header gives only one of width and height")
    return RawHeader(
        fields=tuple(fields),
        size=pos,
        format=found.get("format", (None,))[0],
        width=width,
        height=height,
        has_end=has_end,
    )


def format_header(
    fmt: str, width: int, height: int, extra: dict | None = None
) -> bytes:
    """The header we write: format, geometry (both spellings), extra fields, `% end`.

    **Arguments:**

    - `fmt`: `"evt3"` (the only format we write).
    - `width`, `height`: sensor geometry in pixels.
    - `extra`: more `key: value` fields (single-line strings).

    **Returns:** the header bytes, ending with `% end\\n`.
    """
    if fmt != "evt3":
        raise ValueError(f"cannot write format {fmt!r}; only EVT 3.0")
    lines = [
        "% evt 3.0",
        f"% format EVT3;height={height};width={width}",
        f"% geometry {width}x{height}",
    ]
    for key, value in (extra or {}).items():
        key, value = str(key), str(value)
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", key) or "\n" in value or "\r" in value:
            raise ValueError(f"header field {key!r} must be one word and one line")
        lines.append(f"% {key} {value}")
    lines.append("% end")
    return ("\n".join(lines) + "\n").encode("utf-8")
