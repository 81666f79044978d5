"""Streaming reconstruction: a long recording → one cube per sweep, resumable.

**Dataset format** (a folder; no dependency beyond NumPy, each file readable alone):

- `sweep_000000.npz`, `sweep_000001.npz`, …: one *cube file* per sweep (the contract
  format: `cube` (H, W, M) float32 reflectance and `wavelengths_nm` (M,), so `evhsi
  evaluate` / `evhsi render` / :func:`evhsi_jax.load_cube` work on it), plus `srgb`
  (H, W, 3) uint8 preview, `events_per_pixel` (H, W), `kkt` (H, W), and the scalars
  `sweep`, `start_us`, `stop_us`, `events`. Each file describes itself.
- `index.json`: the run's settings and one entry per finished sweep (file, start/stop
  µs, event count, flags); :func:`load_sweep_index`, :func:`iter_sweep_cubes`.
- `preview.gif`: the sRGB sequence (written when the run completes).

**Bounded memory.** The event file is read chunk by chunk (`iter_events`); only the
sweep being assembled, one decoded chunk and an `(H, W)` per-pixel state are held, so
memory does not grow with the recording (`.npz` event files are the exception: NumPy
loads them whole — convert long recordings to `.raw`).

**Resumable.** Every sweep file is written atomically (temporary file + rename) before
the index mentions it, and the index is rewritten atomically (at most once a second,
and when the run stops for any reason). A crash or Ctrl-C loses at most the sweep in
flight; a rerun with the same inputs and settings skips every sweep whose file exists
(files the index had not caught up with are adopted from their own metadata), and no
file is ever left half-written. A rerun with other inputs or settings into the same
folder is refused (`overwrite=True` starts afresh). Each index entry carries the
sha256 of its sweep file; a resume redoes any sweep whose file no longer matches
(bit rot, a file replaced by hand). One run at a time: the folder is locked
(`.evhsi.lock`, released by the kernel however the run ends) and a second run into it
is refused; temporary files that a killed run left are removed by the next.

**Per-sweep reference.** The first event of a pixel in sweep k refers to the pixel's
reference level, set at the release $τ + η$ after its *last event before the sweep*
(usually the final OFF event as the band left it in sweep k − 1). That level is
$a(τ+η)\\cdot x + c'$: the band's tail on the pixel then, which is up to one threshold
above the baseline c'. The per-sweep solve carries that time per pixel (an `(H, W)`
array updated from every event, skipped sweeps included) and models the level with the
spectrum being solved for — exact for a static scene, and for a moving one off only
where the pixel's material changed between the two sweeps (a level within one threshold
of the baseline either way). Taking the baseline at the sweep start instead is wrong
by up to one threshold on that first constraint: on the moving ColorChecker of
experiments/VIDEO.md it raised the per-sweep SAM of sweeps 1–5 from 1.9–2.4° to
12.6–17.9°. Pixels that never fired before use the baseline, which is exact at the
recording start.

**Flags.** A sweep with fewer than `low_event_rel` × the median events per sweep (no
light, occlusion, a dropped stretch of data) is marked `low_events` in the index (the
median over the sweeps done so far while running, over all at the end); a sweep longer
than 1.5 median trigger intervals (a missed trigger) is marked `irregular`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from .._base import TEMP_SUFFIX, atomic_write, read_npz
from .._io import (
    DEFAULT_CHUNK_BYTES,
    EventReader,
    SweepCutter,
    cube_to_srgb,
    load_cube,
    save_cube,
)
from .._model import Calibration, EventStream, Rig, check_roi
from .._reconstruct import (
    TIMESTAMP_CENTRE_US,
    ProblemConfig,
    reconstruct,
    solver_spec,
    warp_times,
)
from ._store import VideoStore, is_video_store

__all__ = [
    "StreamResult",
    "reconstruct_sweeps",
    "load_sweep_index",
    "iter_sweep_cubes",
    "sweep_file_name",
    "write_preview_gif",
    "convert_sweeps",
    "INDEX_NAME",
    "PREVIEW_NAME",
]

INDEX_NAME = "index.json"
PREVIEW_NAME = "preview.gif"
FORMAT = "evhsi-sweep-cubes"
VERSION = 1


def sweep_file_name(k: int) -> str:
    """The file of sweep `k` inside the dataset folder."""
    return f"sweep_{int(k):06d}.npz"


@dataclasses.dataclass(frozen=True)
class StreamResult:
    """What a :func:`reconstruct_sweeps` run did.

    - `out_dir`: the dataset folder; `index`: the final index (as in `index.json`).
    - `sweeps`: sweeps in the recording (or up to `max_sweeps`).
    - `reconstructed`, `skipped`: solved in this run / found finished already.
    - `low_event_sweeps`: indices flagged `low_events`.
    - `seconds`: wall time of this run; `solve_seconds`: of its solves alone.
    - `stale_removed`: temporary files of killed runs removed from the folder.
    - `decode`: the event file's decode counters (`DecodeReport.as_dict`; None for an
      in-memory stream).
    - `stray_events`: stray events inside lit intervals the sweeps of this run
      removed (`ReconstructionInfo.stray_events`, summed).
    """

    out_dir: Path
    index: dict
    sweeps: int
    reconstructed: int
    skipped: int
    low_event_sweeps: list
    seconds: float
    solve_seconds: float
    stale_removed: int = 0
    decode: dict | None = None
    stray_events: int = 0


# --- index --------------------------------------------------------------------------
def _fingerprint(settings: dict) -> str:
    blob = json.dumps(settings, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _digest(a) -> str | None:
    if a is None:
        return None
    return hashlib.sha256(np.ascontiguousarray(a, np.float64).tobytes()).hexdigest()[
        :16
    ]


def _write_json(path: Path, obj) -> None:
    data = json.dumps(obj, indent=1).encode()
    atomic_write(path, lambda f: f.write(data))


def load_sweep_index(out_dir: str | os.PathLike) -> dict:
    """Read a per-sweep dataset's `index.json` (a clear `ValueError` if it is not one).

    **Returns:** the index: `height`, `width`, `wavelengths_nm`, `period_us`,
    `boundaries` (`"trigger"` / `"period"`), `median_events`, `complete`, and
    `sweeps`, a list of entries `{sweep, file, start_us, stop_us, events, events_rel,
    low_events, irregular, pixels_solved, seconds}` in sweep order.
    """
    if is_video_store(out_dir):
        index = VideoStore(out_dir, "r").index
        if not isinstance(index, dict) or index.get("format") != FORMAT:
            raise ValueError(f"{out_dir} holds no evhsi index: not a per-sweep store")
        return index
    path = Path(out_dir) / INDEX_NAME
    if not path.is_file():
        raise ValueError(f"{out_dir} holds no {INDEX_NAME}: not a per-sweep dataset")
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path} is not readable JSON ({err})") from None
    if index.get("format") != FORMAT:
        raise ValueError(f"{path} is not an {FORMAT} index")
    return index


def iter_sweep_cubes(out_dir: str | os.PathLike) -> Iterator[tuple[dict, dict]]:
    """`(entry, cube_file)` per finished sweep, in order, one file in memory at a time
    (`cube_file` as :func:`evhsi_jax.load_cube` returns it)."""
    index = load_sweep_index(out_dir)
    if is_video_store(out_dir):
        video = VideoStore(out_dir, "r")
        for entry in index["sweeps"]:
            yield entry, video.cube_file(entry["position"])
        return
    for entry in index["sweeps"]:
        yield entry, load_cube(Path(out_dir) / entry["file"])


def _entry_from_file(path: Path) -> dict | None:
    """An index entry rebuilt from a sweep file's own metadata (None if unusable)."""
    try:  # reading every member checks the zip CRCs: a damaged file fails here
        d = read_npz(path, "sweep file")
        meta = {k: int(d[k]) for k in ("sweep", "start_us", "stop_us", "events")}
        meta["pixels_solved"] = int(np.count_nonzero(d["events_per_pixel"]))
    except (ValueError, KeyError, TypeError):  # foreign or damaged: redo that sweep
        return None
    return {"file": path.name, **meta, "seconds": None, "sha256": _file_digest(path)}


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


LOCK_NAME = ".evhsi.lock"


class _FolderLock:
    """An exclusive advisory lock on a dataset folder (`fcntl.flock` on a lock file).

    The kernel releases it when the process ends, however it ends (SIGKILL included),
    so a killed run never blocks the next one. A second run into a locked folder is
    refused at once. Without `fcntl` (Windows) no lock is taken.
    """

    def __init__(self, folder: Path):
        self.path = folder / LOCK_NAME
        self.fd = None

    def __enter__(self):
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not a POSIX system
            return self
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            owner = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise ValueError(
                f"{self.path.parent} is in use by another evhsi run (pid {owner}); "
                "wait for it or use another folder"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self.fd = fd
        return self

    def __exit__(self, *exc):
        if self.fd is not None:
            os.close(self.fd)  # releases the lock; the file stays (harmless)
            self.fd = None


def _remove_stale_temporaries(folder: Path) -> int:
    """Delete the temporary files that killed runs left (`atomic_write`'s
    `.<name>.<random>.tmp`); only called with the folder's lock held."""
    n = 0
    for f in folder.glob(f".*{TEMP_SUFFIX}"):
        name = f.name[1:]
        if name.startswith(("sweep_", INDEX_NAME, PREVIEW_NAME)):
            f.unlink(missing_ok=True)
            n += 1
    return n


def _mark_sweep_quality(entries: list[dict], rel: float, period: float) -> float:
    """Set `events_rel`, `low_events`, `irregular` on every entry; return the median."""
    if not entries:
        return 0.0
    counts = np.array([e["events"] for e in entries], np.float64)
    med = float(np.median(counts))
    lengths = np.array([e["stop_us"] - e["start_us"] for e in entries], np.float64)
    typical = float(np.median(lengths)) if lengths.size else period
    for e, c, n in zip(entries, counts, lengths):
        e["events_rel"] = round(c / med, 4) if med > 0 else 0.0
        e["low_events"] = bool(c < rel * med or c == 0)
        e["irregular"] = bool(n > 1.5 * typical)
    return med


def _writer_lock(out_dir: Path, video: VideoStore | None):
    if video is None:
        return _FolderLock(out_dir)

    @contextlib.contextmanager
    def held():
        video.lock()
        try:
            yield
        finally:
            video.unlock()

    return held()


def _finished_in_store(video: VideoStore, fp: str, *, overwrite: bool) -> dict:
    """Sweeps a previous run of the same inputs and settings finished in a video
    store (its complete sweeps after `repair`), as for `_finished_sweeps`."""
    if overwrite:
        video.clear()
        return {}
    old = video.index
    if old is None:
        if list(video.group.array_keys()):
            raise ValueError(
                f"{video.path} holds arrays but no evhsi index; use another store or "
                "overwrite (--restart)"
            )
        return {}
    if old.get("fingerprint") != fp:
        raise ValueError(
            f"{video.path} holds sweeps of other inputs or settings; use another "
            "store, or overwrite (--restart) to start afresh"
        )
    seconds = {e["sweep"]: e.get("seconds") for e in old.get("sweeps", [])}
    done = {}
    for e in video.entries():
        e["seconds"] = seconds.get(e["sweep"])
        done[e["sweep"]] = e
    return done


def _finished_sweeps(out_dir: Path, fp: str, *, overwrite: bool) -> dict[int, dict]:
    """Sweeps a previous run of the same inputs and settings finished in `out_dir`.

    The index is written before any sweep file, so sweep files without an index are
    foreign: refused, like an index of other settings. Files newer than the index (it
    is rewritten at most once a second) are adopted from their own metadata.
    """
    files = sorted(out_dir.glob("sweep_*.npz")) if out_dir.is_dir() else []
    index_path = out_dir / INDEX_NAME
    if overwrite:
        for f in [*files, index_path, out_dir / PREVIEW_NAME]:
            f.unlink(missing_ok=True)
        return {}
    if not index_path.is_file():
        if files:
            raise ValueError(
                f"{out_dir} holds sweep files but no {INDEX_NAME}; use another folder "
                "or overwrite (--restart)"
            )
        return {}
    old = load_sweep_index(out_dir)
    if old.get("fingerprint") != fp:
        raise ValueError(
            f"{out_dir} holds sweeps of other inputs or settings; use another folder, "
            "or overwrite (--restart) to start afresh"
        )
    done = {}
    for e in old["sweeps"]:  # trust a finished file only if its checksum agrees
        f = out_dir / e["file"]
        if f.is_file() and e.get("sha256") == _file_digest(f):
            done[int(e["sweep"])] = e
    for f in files:
        tail = f.stem.removeprefix("sweep_")
        if (
            tail.isdigit()
            and int(tail) not in done
            and f.name == sweep_file_name(int(tail))
            and not any(e["file"] == f.name for e in old["sweeps"])  # failed its check
        ):
            e = _entry_from_file(f)
            if e is not None and e["sweep"] == int(tail):
                done[int(tail)] = e
    return done


# --- the run -------------------------------------------------------------------------
def _chunks_of(source, chunk_bytes, strict=False, follow=None):
    """`(reader, chunks)`: the file's reader (None for a stream; its `report` fills
    as the chunks are read) and the chunk iterator (`follow`: keyword arguments of
    `EventReader.follow`, for a file still being written)."""
    if isinstance(source, EventStream):
        if follow is not None:
            raise ValueError("follow applies to a .raw file being written")
        return None, source.split(max(1, chunk_bytes // 2))
    if follow is not None:  # a live recording may not have been created yet
        wait_for_file(Path(source), follow.get("idle_timeout_s"), follow.get("should_stop"))
    reader = EventReader(source, chunk_bytes=chunk_bytes, strict=strict)
    if follow is not None:
        return reader, reader.follow(**follow)
    return reader, iter(reader)


def wait_for_file(path: Path, timeout_s, should_stop=None, poll_s: float = 0.05):
    """Wait until `path` exists and holds bytes (the recorder has started), at most
    `timeout_s` (None: 10 s); then the caller opens it or reports it missing."""
    deadline = time.monotonic() + (10.0 if timeout_s is None else float(timeout_s))
    while time.monotonic() < deadline and not (should_stop and should_stop()):
        if path.is_file() and path.stat().st_size > 0:
            return
        time.sleep(poll_s)


def _source_info(source, live: bool = False) -> dict:
    if isinstance(source, EventStream):
        t = source.t_us
        return {
            "path": None,
            "events": len(source),
            "first_us": int(t[0]) if t.size else None,
            "last_us": int(t[-1]) if t.size else None,
        }
    p = Path(source)
    if not p.is_file():
        raise ValueError(f"event file not found: {p}")
    return {"path": p.name, "bytes": "live" if live else p.stat().st_size}


def _gif_bytes(frames: list[np.ndarray], fps: float) -> bytes:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    buf = io.BytesIO()
    images[0].save(
        buf,
        format="GIF",
        save_all=True,
        append_images=images[1:],
        duration=max(20, int(round(1000.0 / fps))),
        loop=0,
    )
    return buf.getvalue()


def convert_sweeps(src: str | os.PathLike, dst: str | os.PathLike) -> int:
    """Copy a per-sweep dataset (folder or store) into a new video store `dst`
    (`.zarr`), sweep by sweep with bounded memory; returns the number of sweeps.

    The store gets its index last, so an interrupted conversion leaves a store that
    every reader refuses (no index) rather than a silently shorter video."""
    index = load_sweep_index(src)
    dst = Path(dst)
    if not is_video_store(dst):
        raise ValueError(f"{dst}: a video store must end in .zarr")
    if dst.exists() and any(dst.iterdir()):
        raise ValueError(f"{dst} exists and is not empty")
    if not dst.parent.is_dir():
        raise ValueError(f"cannot create {dst}: {dst.parent} does not exist")
    video = VideoStore(dst, "a")
    with _writer_lock(dst, video):
        video.prepare(index["height"], index["width"], index["wavelengths_nm"])
        entries = []
        for entry, data in iter_sweep_cubes(src):
            e = {**entry, "file": None, "position": len(video)}
            srgb = data.get("srgb")
            if srgb is None:
                srgb = np.round(255 * cube_to_srgb(data["cube"], data["wavelengths_nm"]))
            video.append(
                e, data["cube"], srgb, data["events_per_pixel"], data["kkt"]
            )
            entries.append(e)
        video.set_index({**index, "sweeps": entries, "preview": None})
    return len(entries)


def write_preview_gif(
    out_dir: str | os.PathLike,
    path: str | os.PathLike | None = None,
    *,
    fps: float | None = None,
    max_width: int = 320,
    max_frames: int = 300,
) -> Path | None:
    """Write the sRGB sequence of a per-sweep dataset as an animated GIF.

    Frames are the sweep files' `srgb` previews, shrunk by an integer factor to at most
    `max_width` pixels and thinned evenly to at most `max_frames` (a GIF holds all
    frames in memory); `fps` defaults to the sweep rate, capped at 50 (GIF timing is in
    10 ms steps). Returns the path, or None when there are no sweeps.
    """
    out_dir = Path(out_dir)
    index = load_sweep_index(out_dir)
    entries = index["sweeps"]
    if not entries:
        return None
    path = Path(path) if path is not None else out_dir / PREVIEW_NAME
    step = max(1, math.ceil(len(entries) / max_frames))
    shrink = max(1, math.ceil(index["width"] / max_width))
    frames = []
    video = VideoStore(out_dir, "r") if is_video_store(out_dir) else None
    for e in entries[::step]:
        if video is not None:
            srgb = np.asarray(video.group["srgb"][e["position"]])
        else:
            srgb = read_npz(out_dir / e["file"], "sweep file")["srgb"]
        frames.append(srgb[::shrink, ::shrink])
    rate = fps or min(50.0, 1e6 / index["period_us"] / step)
    data = _gif_bytes(frames, rate)
    atomic_write(path, lambda f: f.write(data))
    return path


def reconstruct_sweeps(
    source: str | os.PathLike | EventStream,
    calibration: Calibration | Rig,
    out_dir: str | os.PathLike,
    *,
    solver: str = "auto",
    config: ProblemConfig | None = None,
    threshold_on_map: np.ndarray | None = None,
    threshold_off_map: np.ndarray | None = None,
    triggers: str = "auto",
    period_us: float | None = None,
    phase_us: float | None = None,
    max_sweeps: int | None = None,
    low_event_rel: float = 0.5,
    chunk_bytes: int = DEFAULT_CHUNK_BYTES,
    chunk_pixels: int | None = None,
    sub_batch: int | None = None,
    mesh=None,
    preview: bool = True,
    overwrite: bool = False,
    progress: bool = False,
    on_sweep: Callable[[dict], None] | None = None,
    index_interval_s: float = 1.0,
    strict: bool = False,
    follow: bool = False,
    idle_timeout_s: float = 10.0,
    should_stop: Callable[[], bool] | None = None,
    roi: tuple[int, int, int, int] | None = None,
    deblur: bool | None = None,
    backend: str = "auto",
    threads: int | None = None,
    sweep_speed: str = "auto",
) -> StreamResult:
    """Reconstruct every sweep of a recording into its own cube file (resumable).

    See the module docstring for the dataset format, the memory bound, resuming and
    the per-sweep reference.

    **Arguments:**

    - `source`: an event file (`.raw` EVT 3.0/2.0 streamed in chunks, or `.npz`) or an
      in-memory :class:`EventStream`.
    - `calibration`: a :class:`Calibration` (or a bare rig); `threshold_on_map`,
      `threshold_off_map`: optional per-pixel thresholds `(H, W)`, log units, that
      override the calibration's.
    - `out_dir`: the dataset folder (created; its parent must exist).
    - `solver`, `config`, `chunk_pixels`, `sub_batch`, `mesh`, `deblur`: as for
      :func:`evhsi_jax.reconstruct` (`mesh` shards each sweep's pixels over devices).
    - `sweep_speed`: `"auto"` (each sweep's mirror speed measured from its events,
      as `reconstruct` does; the index entry's `sweep_speed` has the factor) or
      `"off"`. The next sweep's carried references are then at the times the
      factor gives the last events.
    - `triggers`: `"auto"` (encoder triggers if the first periods hold any, else the
      period), `"require"` or `"ignore"`; without triggers, sweeps start at
      `phase_us + j period_us` (defaults 0 and the rig's period; the band's sweep
      origin, as `reconstruct`'s `t_start_us` — not a cut in the dead time).
    - `max_sweeps`: stop after this many sweeps (default: all).
    - `low_event_rel`: flag sweeps with fewer events than this × the median.
    - `chunk_bytes`: bytes decoded per read (bounds the reader's memory).
    - `preview`: write `preview.gif` when the run completes.
    - `overwrite`: discard a dataset of other inputs/settings in `out_dir` instead of
      refusing.
    - `progress`: show a progress bar (sweeps/s).
    - `on_sweep`: called with each finished sweep's index entry once its file is
      written (an exception raised there stops the run like a crash would).
    - `index_interval_s`: the least time between two index rewrites.
    - `strict`: stop at the first defect of the event file (see `EventReader`).
    - `follow`: the `.raw` file is still being written (live capture): read what
      arrives, reconstruct each sweep as soon as the next one starts (or the
      recording ends), and stop when the file has not grown for `idle_timeout_s`
      seconds or `should_stop()` returns True (`EventReader.follow`). The cubes are
      those of the same run on the finished file. A live run's settings record the
      source as `live` (not its size), so it resumes with `follow` again.
    - `roi`: `(x0, y0, x1, y1)`, reconstruct only this region (half-open, pixels);
      cubes are the region's size (the calibration is cut to it: `Calibration.crop`).

    **Returns:** a :class:`StreamResult`.
    """
    from .._base import is_main_process

    t_run = time.perf_counter()
    out_dir = Path(out_dir)
    if not out_dir.parent.is_dir():
        raise ValueError(f"cannot create {out_dir}: {out_dir.parent} does not exist")
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"{out_dir} exists and is not a folder")
    if not 0 <= low_event_rel < 1:
        raise ValueError(f"low_event_rel must be in [0, 1), got {low_event_rel}")
    if triggers not in ("auto", "require", "ignore"):
        raise ValueError(f"triggers must be auto, require or ignore, not {triggers!r}")
    if max_sweeps is not None and max_sweeps < 1:
        raise ValueError(f"max_sweeps must be >= 1, got {max_sweeps}")
    writer = is_main_process()
    cal = calibration if isinstance(calibration, Calibration) else Calibration(calibration)
    live = (
        dict(idle_timeout_s=idle_timeout_s, should_stop=should_stop) if follow else None
    )
    reader, chunks = _chunks_of(source, chunk_bytes, strict, live)
    if roi is not None:  # a region: its events, its columns' offsets, its maps
        full = reader if reader is not None else source
        roi = check_roi(roi, full.width, full.height)
        if threshold_on_map is not None:
            cal = dataclasses.replace(
                cal, threshold_on=threshold_on_map, threshold_off=threshold_off_map
            )
            threshold_on_map = threshold_off_map = None
        cal = cal.crop(roi, full.width)
        chunks = (c.crop(roi) for c in chunks)
    rig = cal.rig
    if threshold_on_map is None and cal.threshold_on is not None:
        threshold_on_map, threshold_off_map = cal.threshold_on, cal.threshold_off
    spec = solver_spec(solver)
    cfg = config or ProblemConfig()
    period = float(period_us) if period_us else float(rig.period_us)
    eta = float(rig.refractory_us)

    cutter = SweepCutter(chunks, period, triggers, phase_us)
    sweeps_iter = iter(cutter)
    try:
        first = next(sweeps_iter)
    except StopIteration:
        raise ValueError(f"{source} holds no events") from None
    w, h = cutter.geometry
    settings = {
        "source": _source_info(source, live=follow),
        "rig": rig.to_dict(width=w),
        "solver": dataclasses.asdict(spec),
        "config": dataclasses.asdict(cfg),
        "threshold_maps": [_digest(threshold_on_map), _digest(threshold_off_map)],
        "boundaries": cutter.mode,
        "period_us": period,
        "phase_us": cutter.phase,
        "reference": "carry",
    }
    if roi is not None:  # (absent otherwise: older datasets keep their fingerprint)
        settings["roi"] = list(roi)
    if deblur is not None:  # (absent by default: older datasets keep their fingerprint)
        settings["deblur"] = bool(deblur)
    if sweep_speed not in ("auto", "off"):
        raise ValueError(f"sweep_speed must be 'auto' or 'off', not {sweep_speed!r}")
    if sweep_speed != "auto":  # (likewise)
        settings["sweep_speed"] = sweep_speed
    fp = _fingerprint(settings)

    out = _SweepOutput(out_dir, writer, index_interval_s)
    # One writer per folder: a second run refuses instead of mixing its sweeps in.
    with out.lock():
        stale, done = out.open(fp, overwrite, h, w, rig.wavelengths_nm)
        index = out.new_index(
            fp, settings, h, w, rig, period, cutter.mode, low_event_rel
        )
        carry = _ReferenceCarry(h, w, eta, rig.column_offsets(w), float(rig.period_us))
        n_new = n_skip = 0
        solve_s = 0.0
        strays = 0
        bar = tqdm(disable=not progress, unit="sweep", desc="reconstruct sweeps")
        try:
            out.commit(force=True)
            for k, start, stop, ev, before in _chain([first], sweeps_iter):
                if max_sweeps is not None and k >= max_sweeps:
                    break
                carry.add(before)
                if k in done and done[k]["start_us"] == start:
                    n_skip += 1
                    carry.add(ev, start, done[k].get("sweep_speed"))
                    bar.update(1)
                    continue
                t0 = time.perf_counter()
                cube, info = reconstruct(
                    ev,
                    cal,
                    solver=spec,
                    config=cfg,
                    threshold_on_map=threshold_on_map,
                    threshold_off_map=threshold_off_map,
                    t_start_us=start,
                    reference_us=carry.reference_us(),
                    chunk_pixels=chunk_pixels,
                    sub_batch=sub_batch,
                    mesh=mesh,
                    return_info=True,
                    deblur=deblur,
                    backend=backend,
                    threads=threads,
                    sweep_speed=sweep_speed,
                )
                dt = time.perf_counter() - t0
                solve_s += dt
                strays += info.stray_events
                factor = None if info.sweep_speed is None else float(info.sweep_speed[0])
                carry.add(ev, start, factor)
                entry = out.write_sweep(k, start, stop, ev, cube, info, dt, rig)
                n_new += 1
                bar.update(1)
                bar.set_postfix_str(f"{h * w / max(dt, 1e-9):,.0f} px/s", refresh=False)
                out.commit()
                if on_sweep is not None:
                    on_sweep(dict(entry))
            index["complete"] = True  # every sweep (up to max_sweeps) is done
        finally:
            bar.close()
            out.commit(force=True)
        if preview:
            out.write_preview()
    entries = index["sweeps"]
    return StreamResult(
        out_dir=out_dir,
        index=index,
        sweeps=len(entries),
        reconstructed=n_new,
        skipped=n_skip,
        low_event_sweeps=[e["sweep"] for e in entries if e["low_events"]],
        seconds=time.perf_counter() - t_run,
        solve_seconds=solve_s,
        stale_removed=stale,
        decode=None if reader is None else reader.report.as_dict(),
        stray_events=strays,
    )


class _ReferenceCarry:
    """Each pixel's last event time so far, carried from sweep to sweep: the next
    sweep's first event of a pixel refers to the release after it (module docstring,
    "per-sweep reference"). A sweep read with a mirror-speed factor
    (`reconstruct(sweep_speed=...)`) leaves its events' times as the factor moved
    them (:func:`evhsi_jax._reconstruct._sweep_speed.warp_times`): the reference
    lies where the band leaves the pixel, on a steep flank."""

    def __init__(self, h: int, w: int, eta_us: float, offsets_us, period_us: float):
        self.h, self.w, self.eta = h, w, eta_us
        self.offsets = np.asarray(offsets_us, np.float64)
        self.period = period_us
        self.last_t = np.full(h * w, np.nan)  # (event time + TIMESTAMP_CENTRE_US)

    def add(self, ev: EventStream | None, start=None, factor=None) -> None:
        if ev is None or not len(ev):
            return
        pix = ev.y.astype(np.int64) * self.w + ev.x.astype(np.int64)
        t = ev.t_us.astype(np.float64) + TIMESTAMP_CENTRE_US
        if factor is not None and factor != 1.0:
            t = start + warp_times(
                t - start, ev.x.astype(np.int64), self.offsets, self.period, [factor]
            )  # fmt: skip
        np.fmax.at(self.last_t, pix, t)

    def reference_us(self) -> np.ndarray:
        return (self.last_t + self.eta).reshape(self.h, self.w)


class _SweepOutput:
    """Where the sweeps of a run go: a folder of cube files with `index.json`, or a
    Zarr video store; resuming (the finished sweeps of the same settings), the index
    and its rate-limited rewrites, the preview. Processes other than the main one
    (multi-process runs) compute but write nothing."""

    def __init__(self, out_dir: Path, writer: bool, index_interval_s: float):
        self.dir, self.writer, self.interval = out_dir, writer, index_interval_s
        self.video: VideoStore | None = None
        if writer and is_video_store(out_dir):
            self.video = VideoStore(out_dir, "a")
        elif writer:
            out_dir.mkdir(exist_ok=True)
        self.done: dict[int, dict] = {}
        self.index: dict = {}
        self._last_write = 0.0

    def lock(self):
        if not self.writer:
            return contextlib.nullcontext()
        return _writer_lock(self.dir, self.video)

    def open(self, fp: str, overwrite: bool, h: int, w: int, wavelengths):
        """Repair what a crash left and read the sweeps already finished with these
        settings: `(stale files removed, {sweep: index entry})`."""
        if self.video is not None:
            stale = self.video.repair()
            self.done = _finished_in_store(self.video, fp, overwrite=overwrite)
            self.video.prepare(h, w, wavelengths)
        else:
            stale = _remove_stale_temporaries(self.dir) if self.writer else 0
            self.done = _finished_sweeps(
                self.dir, fp, overwrite=overwrite and self.writer
            )
        return stale, self.done

    def new_index(self, fp, settings, h, w, rig, period, mode, low_event_rel) -> dict:
        self.index = {
            "format": FORMAT,
            "version": VERSION,
            "fingerprint": fp,
            "complete": False,
            "height": h,
            "width": w,
            "channels": rig.channels,
            "wavelengths_nm": [float(v) for v in rig.wavelengths_nm],
            "period_us": period,
            "boundaries": mode,
            "reference": "carry: first event of a sweep refers to the release after the "
            "pixel's last earlier event",
            "low_event_rel": low_event_rel,
            "median_events": 0.0,
            "preview": None,
            "settings": settings,
            "sweeps": [],
        }
        return self.index

    def commit(self, force: bool = False) -> None:
        """Rewrite the index (at most every `index_interval_s` unless forced)."""
        if not self.writer:
            return
        now = time.perf_counter()
        if not force and now - self._last_write < self.interval:
            return
        entries = [self.done[k] for k in sorted(self.done)]
        self.index["median_events"] = _mark_sweep_quality(
            entries, self.index["low_event_rel"], self.index["period_us"]
        )
        self.index["sweeps"] = entries
        if self.video is not None:
            self.video.set_index(self.index)
        else:
            _write_json(self.dir / INDEX_NAME, self.index)
        self._last_write = now

    def write_sweep(self, k, start, stop, ev, cube, info, seconds, rig) -> dict:
        """Store sweep `k`'s cube and return its index entry."""
        video = self.video
        if video is not None and k < len(video):
            raise ValueError(
                f"{self.dir}: sweep {k} is in the store with another start time"
            )
        entry = {
            "sweep": k,
            "file": None if video is not None else sweep_file_name(k),
            "start_us": int(start),
            "stop_us": int(stop),
            "events": len(ev),
            "pixels_solved": int(info.solved.sum()),
            "seconds": round(seconds, 4),
        }
        if info.sweep_speed is not None:  # (the mirror-speed factor it was read with)
            entry["sweep_speed"] = float(info.sweep_speed[0])
        if self.writer:
            srgb = np.round(255 * cube_to_srgb(cube, rig.wavelengths_nm))
        if video is not None:
            entry["position"] = len(video)
            video.append(entry, cube, srgb, info.events, info.kkt)
        elif self.writer:
            save_cube(
                self.dir / entry["file"],
                cube,
                rig.wavelengths_nm,
                srgb=srgb.astype(np.uint8),
                events_per_pixel=info.events.astype(np.int32),
                kkt=info.kkt,
                sweep=np.int64(k),
                start_us=np.int64(start),
                stop_us=np.int64(stop),
                events=np.int64(len(ev)),
            )
            entry["sha256"] = _file_digest(self.dir / entry["file"])
        self.done[k] = entry
        return entry

    def write_preview(self) -> None:
        """`preview.gif` of a complete folder run (not for a video store)."""
        if self.writer and self.video is None and self.index["complete"] and self.done:
            gif = write_preview_gif(self.dir)
            self.index["preview"] = gif.name if gif else None
            self.commit(force=True)


def _chain(*its):
    for it in its:
        yield from it
