"""Files on disk: written whole or not at all, never over an input, read with errors
that name the file.

Every module that writes a file goes through :func:`atomic_write`; every `.npz` a user
hands us goes through :func:`read_npz`, so a truncated, bit-flipped or mislabelled file
is a `ValueError` naming it (the CLI's exit 2), not an internal error;
:func:`check_outputs` is what the CLI runs before any computation: no output may be one
of the command's inputs (same path or same inode, links included), no two outputs may
be one file, and every output's folder must exist and be writable.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["atomic_write", "read_npz", "check_outputs", "same_file", "TEMP_SUFFIX"]

TEMP_SUFFIX = ".tmp"


def atomic_write(path: str | os.PathLike, write) -> None:
    """Write a file whole or not at all.

    `write(fileobj)` fills a temporary file `.<name>.<random>.tmp` in the destination
    folder, which is then renamed over `path`; on any error the temporary file is
    removed and `path` is left as it was. (A process killed outright leaves the
    temporary file behind; the per-sweep writer removes such leftovers.)
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"cannot write {path}: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMP_SUFFIX, dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        # mkstemp creates 0600; give the file the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def read_npz(path: str | os.PathLike, what: str = "file") -> dict[str, np.ndarray]:
    """Every array of an `.npz` file, read in full (no pickles).

    A missing, truncated, corrupted or non-`.npz` file (e.g. a `.npy` renamed) raises a
    `ValueError` that names the file and what it should have been (`what`).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{what} not found: {path}")
    errors = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)
    with open(path, "rb") as fh:  # ours to close, whatever np.load makes of it
        try:
            data = np.load(fh, allow_pickle=False)
        except errors as err:
            raise ValueError(
                f"{path} is not a readable .npz {what} ({one_line(err)})"
            ) from None
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError(
                f"{path} is not an .npz archive (a bare .npy array?); expected a {what}"
            )
        try:
            with data:
                return {k: np.asarray(data[k]) for k in data.files}
        except errors as err:
            raise ValueError(
                f"{path} is not a readable .npz {what}: a member is damaged or holds "
                f"objects ({one_line(err)})"
            ) from None


def scalar_int(arrays: Mapping[str, np.ndarray], key: str, path) -> int:
    """`arrays[key]` as a Python int; a `ValueError` naming the file when it is not a
    single integer (an array, a float with a fraction, a string)."""
    value = np.asarray(arrays[key])
    if value.size != 1 or not (
        np.issubdtype(value.dtype, np.integer)
        or (np.issubdtype(value.dtype, np.floating) and float(value) == int(value))
    ):
        raise ValueError(f"{path}: {key!r} must be one integer, got {value!r:.60}")
    return int(value.reshape(()))


def one_line(err: BaseException, limit: int = 120) -> str:
    """An exception's message on one line, at most `limit` characters (its type's
    name when it has none): what error messages quote of a library's exception."""
    return " ".join(str(err).split())[:limit] or type(err).__name__


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when `a` and `b` name one file: equal resolved paths, or (both existing)
    the same inode (hard links, symlinks, bind mounts)."""
    a, b = Path(a), Path(b)
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(
    inputs: Mapping[str, str | os.PathLike | None],
    outputs: Mapping[str, str | os.PathLike | None],
) -> None:
    """Refuse, before any work, outputs that would destroy an input or each other.

    `inputs` and `outputs` map a name for the user (`"EVENTS"`, `"--out"`, …) to a
    path (None: not given). Raises `ValueError` when an output is an input, two
    outputs are one file, or an output's folder is missing or not writable.
    """
    ins = {k: Path(v) for k, v in inputs.items() if v is not None}
    outs = {k: Path(v) for k, v in outputs.items() if v is not None}
    for name, out in outs.items():
        for iname, inp in ins.items():
            if same_file(out, inp):
                raise ValueError(
                    f"{name} {out} is the input {iname}: refusing to write over an input"
                )
    names = list(outs)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if same_file(outs[a], outs[b]):
                raise ValueError(f"{a} and {b} are the same file {outs[a]}")
    for name, out in outs.items():
        folder = out.parent if str(out.parent) else Path(".")
        if not folder.is_dir():
            raise ValueError(f"{name}: output folder does not exist: {folder}")
        try:  # try it: permissions, read-only mounts and quotas all show here
            fd, probe = tempfile.mkstemp(prefix=".evhsi-probe.", dir=folder)
            os.close(fd)
            os.unlink(probe)
        except OSError as err:
            raise ValueError(
                f"{name}: cannot write into {folder} ({one_line(err)})"
            ) from None
        if out.is_dir() and out.suffix.lower() != ".zarr":  # a Zarr store is a folder
            raise ValueError(f"{name} {out} is a folder, not a file")
