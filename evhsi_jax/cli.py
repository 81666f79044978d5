"""The `evhsi` command-line tool.

Every sub-command validates its inputs and turns a user mistake into one line on stderr
and exit status 2 (no traceback; set EVHSI_DEBUG=1 to see one). Output files are written
whole or not at all.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from ._base import check_outputs, same_file, shard
from ._io import CUBE_SUFFIXES
from ._model import check_roi

__all__ = ["main"]

UNITS = """
units: wavelengths in nm, times in µs (event timestamps are integer µs), thresholds
in natural-log units, reflectance in [0, 1], constant light c as a fraction of a white
pixel's peak intensity.
"""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, not usage + message
        self.exit(2, f"evhsi: error: {message} (see `{self.prog} --help`)\n")


def _add_rig(p):
    p.add_argument(
        "--rig",
        metavar="RIG.json",
        help="rig/calibration JSON; keys left out take the default (paper) rig's value",
    )


def _load_rig(path):
    from ._model import Rig

    # `rig`, `simulate` and `calibrate --init` use no per-pixel maps: a calibration
    # file's rig is read alone (reconstruct takes `--calib`, maps and all).
    return Rig.load(path, maps="ignore") if path else Rig()


def _out_path(path: str, suffixes: tuple[str, ...], what: str) -> Path:
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{what} must end in {' or '.join(suffixes)}, got {path!r}")
    if p.parent and not p.parent.exists():
        raise ValueError(f"output folder does not exist: {p.parent}")
    return p


def _cube_outputs(path, name: str) -> dict:
    """The files a cube output writes (ENVI: the header, image and extras)."""
    if path is None:
        return {}
    path = Path(path)
    if path.suffix.lower() != ".hdr":
        return {name: path}
    return {
        name: path,
        f"{name}'s image": path.with_suffix(".img"),
        f"{name}'s extras": path.with_name(path.stem + ".evhsi.npz"),
    }


def _warn(args, text: str) -> None:
    print(f"evhsi {args.command}: warning: {text}", file=sys.stderr)


def _problems(args, what, problems: list[str], *, fatal: bool = False) -> None:
    """Counted problems of an input: a warning line on stderr, or (with --strict, or
    when `fatal`: the output would be wrong) an error."""
    if not problems:
        return
    text = f"{what}: " + "; ".join(problems)
    if fatal or getattr(args, "strict", False):
        raise ValueError(text + ("" if fatal else " (--strict)"))
    _warn(args, text)


def _read_events(args, path, *, computes: bool = True):
    """Read an event file, reporting what the decoder skipped or clamped. When the
    events feed a computation (`computes`), time jumping back is an error: the
    answer would be wrong (a concatenated recording, say)."""
    from ._io import EventReader

    reader = EventReader(path, strict=getattr(args, "strict", False))
    events = reader.read()
    report = reader.report
    _problems(args, path, report.problems(), fatal=computes and report.time_jumped_back)
    return events


def _decode_problems(counters: dict | None) -> list[str]:
    if not counters:
        return []
    from ._io import DecodeReport

    return DecodeReport(**counters).problems()


def _add_strict(p):
    p.add_argument(
        "--strict",
        action="store_true",
        help="treat counted problems of the input (skipped or out-of-geometry events, "
        "time going back, sweeps left out) as errors instead of warnings",
    )


# --- sub-commands ---------------------------------------------------------------------
def cmd_rig(args):
    from ._model import parse_size

    rig = _load_rig(args.rig)
    h, w = parse_size(args.size) or (720, 1280)
    print(json.dumps(rig.to_dict(width=w), indent=2))
    return 0


def cmd_simulate(args):
    import jax.random as jr

    from ._io import save_cube, write_events
    from ._model import load_scene, parse_size
    from ._simulate import simulate

    out = _out_path(args.out, (".npz", ".raw"), "--out")
    truth = _out_path(args.truth, CUBE_SUFFIXES, "--truth") if args.truth else None
    scene_file = args.scene if str(args.scene).endswith(".npz") else None
    check_outputs(
        {"--rig": args.rig, "--scene": scene_file},
        {"--out": out, **_cube_outputs(truth, "--truth")},
    )
    rig = _load_rig(args.rig)
    if args.sweeps < 1:
        raise ValueError(f"--sweeps must be >= 1, got {args.sweeps}")
    scene = load_scene(args.scene, parse_size(args.size))
    seed = int(rig.seed) if args.seed is None else args.seed
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    t0 = time.perf_counter()
    events, info = simulate(
        scene,
        rig,
        sweeps=args.sweeps,
        progress=not args.quiet,
        return_info=True,
        key=jr.key(seed),
    )
    elapsed = time.perf_counter() - t0
    write_events(out, events)
    if truth is not None:
        save_cube(
            truth,
            scene.truth_cube(rig.grid),
            rig.wavelengths_nm,
            labels=scene.labels,
            names=np.array(scene.names or [""], dtype=str),
            threshold_on=info.threshold_on,
            threshold_off=info.threshold_off,
        )
    n_pix = scene.height * scene.width
    print(
        f"simulated {args.scene} {scene.height}x{scene.width}, {args.sweeps} sweep(s) in "
        f"{elapsed:.1f} s: {len(events):,} events "
        f"({len(events) / n_pix / args.sweeps:.1f} per pixel per sweep, "
        f"{2 * len(events) / 1e6:.2f} MB at 16 bits/event) -> {out}"
        + (f"; truth -> {truth}" if truth else "")
    )
    return 0


def cmd_render(args):
    from ._io import cube_to_srgb, load_cube, write_png

    out = _out_path(args.out, (".png",), "--out")
    check_outputs({"CUBE": args.cube}, {"--out": out})
    data = load_cube(args.cube)
    cube = data["cube"]
    bad = ~np.all(np.isfinite(cube), axis=-1)
    if bad.all():
        raise ValueError(f"{args.cube}: no pixel has a finite spectrum; nothing to render")
    if bad.any():
        _problems(
            args,
            args.cube,
            [f"{int(bad.sum())} pixel(s) with NaN/inf values drawn black"],
        )
        cube = np.where(bad[..., None], 0.0, cube)
    write_png(out, cube_to_srgb(cube, data["wavelengths_nm"]))
    print(f"wrote {out}")
    return 0


def cmd_info(args):
    from ._io import describe_events

    info = describe_events(args.events, strict=args.strict)
    _problems(args, args.events, _decode_problems(info.get("decode")))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k:22s} {v}")
    return 0


def _sweep_speed(args):
    """`--sweep-speed` checked: "auto", "off" or a list of factors (one per sweep
    used; with --per-sweep only auto or off)."""
    text = args.sweep_speed.strip()
    if text in ("auto", "off"):
        return text
    if args.per_sweep:
        raise ValueError("with --per-sweep, --sweep-speed is auto or off")
    try:
        factors = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(
            f"--sweep-speed must be auto, off or factors F[,F...], got {text!r}"
        ) from None
    return factors


def cmd_reconstruct(args):
    config = _problem_config(args)  # its options checked before any work
    speed = _sweep_speed(args)
    if args.per_sweep:
        return _reconstruct_per_sweep(args, config, speed)
    if args.max_sweeps is not None or args.restart or args.follow:
        raise ValueError(
            "--max-sweeps, --restart and --follow apply only with --per-sweep"
        )
    from ._io import cube_to_srgb, save_cube, write_png
    from ._model import load_calibration
    from ._reconstruct import reconstruct

    out = _out_path(args.out, CUBE_SUFFIXES, "--out")
    preview = _out_path(args.preview, (".png",), "--preview") if args.preview else None
    check_outputs(
        _calib_inputs(args), {**_cube_outputs(out, "--out"), "--preview": preview}
    )
    cal = _with_channels(load_calibration(args.calib), args.channels)
    rig = cal.rig
    events = _read_events(args, args.events)
    if len(events) == 0:
        raise ValueError(f"{args.events} holds no events")
    if args.roi is not None:
        roi = _parse_roi(args.roi)
        cal = cal.crop(check_roi(roi, events.width, events.height), events.width)
        events = events.crop(roi)
    t0 = time.perf_counter()
    cube, info = reconstruct(
        events,
        cal,
        solver=args.solver,
        config=config,
        t_start_us=args.t_start_us,
        progress=not args.quiet,
        return_info=True,
        # The CUDA kernel runs on one GPU: no mesh unless --devices asks for one.
        mesh=_mesh(1 if args.backend == "cuda" and args.devices is None else args.devices),
        deblur=_DEBLUR[args.deblur],
        backend=args.backend,
        threads=args.threads,
        sweep_speed=speed,
    )
    elapsed = time.perf_counter() - t0
    notes = []
    if info.first_sweep:
        notes.append(
            f"the first {info.first_sweep} sweep(s) from the start hold no events or "
            "too few"
        )
    if info.sweeps_left_out:
        notes.append(
            f"{info.sweeps_left_out} sweep(s) with too few events, or apart from "
            f"the others, left out ({info.events_left_out:,} events)"
        )
    if notes:
        notes[-1] += f"; used {info.sweeps} sweep(s) from {info.t_start_us} µs"
    _problems(args, args.events, notes)
    from ._base import is_main_process

    if is_main_process():  # in a multi-process run, process 0 writes
        save_cube(
            out, cube, rig.wavelengths_nm, events_per_pixel=info.events, kkt=info.kkt
        )
        if preview is not None:
            write_png(preview, cube_to_srgb(cube, rig.wavelengths_nm))
    n = events.height * events.width
    print(
        f"reconstructed {events.height}x{events.width}x{rig.channels} "
        f"({int(info.solved.sum()):,} of {n:,} pixels had events, {info.sweeps} "
        f"sweep(s)) with {args.solver} in {elapsed:.1f} s "
        f"({n / elapsed:,.0f} px/s) -> {out}"
        + (f"; preview -> {preview}" if preview else "")
        + (
            f"; {info.stray_events:,} stray event(s) inside lit intervals removed"
            if info.stray_events
            else ""
        )
        + _speed_note(info.sweep_speed)
    )
    return 0


def _speed_note(factors) -> str:
    """The summary's words on the mirror-speed factors used (none: nothing)."""
    if factors is None:
        return ""
    pct = [f"{100 * (f - 1):+.2f}" for f in factors]
    more = f" (+{len(pct) - 8} more)" if len(pct) > 8 else ""
    return f"; mirror speed per sweep {', '.join(pct[:8])}{more} %"


def _with_channels(cal, channels):
    """The calibration on `--channels` channels (None: its own)."""
    if channels is None:
        return cal
    try:
        return cal.with_channels(channels)
    except ValueError as err:
        raise ValueError(f"--channels: {err}") from None


def _parse_roi(text: str) -> tuple[int, ...]:
    parts = text.split(",")
    if len(parts) != 4 or not all(p.strip().lstrip("-").isdigit() for p in parts):
        raise ValueError(f"--roi must be x0,y0,x1,y1 (4 integers), got {text!r}")
    return tuple(int(p) for p in parts)


def _calib_inputs(args) -> dict:
    """reconstruct's inputs: events, calibration JSON and the maps file it names."""
    ins = {"EVENTS": args.events, "--calib": args.calib}
    try:
        maps = json.loads(Path(args.calib).read_text()).get("threshold_map")
        if isinstance(maps, str):
            ins["the calibration's maps"] = Path(args.calib).parent / maps
    except (OSError, ValueError, AttributeError):
        pass  # load_calibration says what is wrong with the file
    return ins


#: `--devices` default on a CPU: one XLA host device per usable core, at most this many.
MAX_AUTO_CPU_DEVICES = 8


def _cpu_devices(devices) -> None:
    """`--devices N` (N > 1) on a CPU: ask XLA for N host devices, so the pixels can be
    sharded over them and fill the cores (one CPU device keeps ~1.4 of 2 cores busy;
    two ran 1.77x as fast on the 2-core machine in an earlier session). The default
    (`None`, auto) asks for one per usable core, at most `MAX_AUTO_CPU_DEVICES`.
    Must run before JAX creates its backend (in-process callers whose JAX already
    started keep their devices); a device count already in XLA_FLAGS wins. Harmless on
    GPU machines (the GPUs stay the default devices)."""
    if devices is None:
        devices = min(shard.usable_cores(), MAX_AUTO_CPU_DEVICES)
    flags = os.environ.get("XLA_FLAGS", "")
    if devices and devices > 1 and "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (
            f"{flags} --xla_force_host_platform_device_count={devices}".strip()
        )


def _mesh(devices):
    """The pixel mesh of `--devices`: None for one device; auto (None): every local
    device of the default backend that this process has (one GPU: no mesh)."""
    if devices == 1:
        return None
    from ._base import pixel_mesh

    if devices is None:
        import jax

        n = len(jax.local_devices())
        return pixel_mesh(n) if n > 1 else None
    return pixel_mesh(None if devices == 0 else devices)


_DEBLUR = {"auto": None, "on": True, "off": False}


def _problem_config(args):
    """The per-pixel problem's settings that `reconstruct` options change (None:
    the defaults)."""
    stray_z = args.stray_z
    if args.photoreceptor_passes is None and stray_z is None:
        return None
    if args.photoreceptor_passes is not None and not 0 <= args.photoreceptor_passes <= 16:
        raise ValueError(
            f"--photoreceptor-passes must be in [0, 16], got {args.photoreceptor_passes}"
        )
    if stray_z is not None and not (np.isfinite(stray_z) and stray_z >= 0):
        raise ValueError(f"--stray-z must be a finite number >= 0, got {stray_z}")
    from ._reconstruct import ProblemConfig

    kw = {}
    if args.photoreceptor_passes is not None:
        kw["lowpass_passes"] = args.photoreceptor_passes
    if stray_z is not None:
        kw["stray_z"] = stray_z
    return ProblemConfig(**kw)


def _run_sweeps(args, cal, out, roi, stop, config, speed):
    from ._video import reconstruct_sweeps

    return reconstruct_sweeps(
        args.events,
        cal,
        out,
        solver=args.solver,
        config=config,
        max_sweeps=args.max_sweeps,
        low_event_rel=args.low_events,
        # Per sweep, one device unless asked: each sweep is small and latency counts
        # (a sharded kernel per bucket is more to compile and dispatch).
        mesh=None if args.devices is None else _mesh(args.devices),
        overwrite=args.restart,
        progress=not args.quiet,
        strict=args.strict,
        follow=args.follow,
        idle_timeout_s=args.idle_timeout,
        should_stop=lambda: stop["asked"],
        roi=roi,
        deblur=_DEBLUR[args.deblur],
        backend=args.backend,
        threads=args.threads,
        sweep_speed=speed,
    )


def _reconstruct_per_sweep(args, config, speed):
    from ._io import EventReader
    from ._model import load_calibration

    out = Path(args.out)
    if out.suffix and out.suffix.lower() != ".zarr":
        raise ValueError(
            f"with --per-sweep, --out is a folder or a VIDEO.zarr store, got {args.out!r}"
        )
    if args.preview:
        raise ValueError("with --per-sweep the preview is DIR/preview.gif")
    if args.t_start_us is not None:
        raise ValueError("--t-start-us does not apply to --per-sweep")
    ins = _calib_inputs(args)
    for name, path in ins.items():  # inputs must not be files the run manages
        if Path(path).resolve().parent == out.resolve() and (
            Path(path).name.startswith("sweep_")
            or Path(path).name in ("index.json", "preview.gif")
        ):
            raise ValueError(f"{name} {path} lies in the output folder {out}")
        if same_file(path, out):
            raise ValueError(f"--out {out} is the input {name}")
    cal = _with_channels(load_calibration(args.calib), args.channels)
    rig = cal.rig
    if not args.idle_timeout > 0:
        raise ValueError(f"--idle-timeout must be > 0 s, got {args.idle_timeout}")
    if args.follow:  # started before the recorder: wait for the file to appear
        from ._video import wait_for_file

        wait_for_file(Path(args.events), args.idle_timeout)
    reader = EventReader(args.events)  # geometry only; the events are streamed
    cal.check_size(reader.height, reader.width)
    roi = None
    if args.roi is not None:
        roi = check_roi(_parse_roi(args.roi), reader.width, reader.height)
    stop = {"asked": False}
    previous = {}
    if args.follow:  # a signal ends the recording: finish the sweeps, then stop
        import signal

        def end_of_recording(signum, frame):
            if stop["asked"]:
                raise KeyboardInterrupt
            stop["asked"] = True
            print("evhsi reconstruct: stopping at the end of the data read so far "
                  "(again to abort)", file=sys.stderr)  # fmt: skip

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, end_of_recording)
    try:
        res = _run_sweeps(args, cal, out, roi, stop, config, speed)
    finally:  # the handlers are this run's only (main() may be called in-process)
        if previous:
            import signal

            for sig, handler in previous.items():
                signal.signal(sig, handler)
    _problems(args, args.events, _decode_problems(res.decode))
    n = res.index["height"] * res.index["width"]
    rate = res.reconstructed / res.solve_seconds if res.solve_seconds else 0.0
    low = res.low_event_sweeps
    from ._base import is_main_process

    if is_main_process():
        print(
            f"{res.sweeps} sweep(s) of {res.index['height']}x{res.index['width']}x"
            f"{rig.channels} in "
            f"{out}: {res.reconstructed} reconstructed in {res.seconds:.1f} s "
            f"({rate:.2f} sweeps/s, {rate * n:,.0f} px/s), {res.skipped} already done"
            + (f"; {len(low)} flagged low-events: {low[:10]}" if low else "")
            + (
                f"; {res.stray_events:,} stray event(s) inside lit intervals removed"
                if res.stray_events
                else ""
            )
            + _speed_range_note(res.index["sweeps"])
        )
    return 0


def _speed_range_note(entries) -> str:
    """The per-sweep summary's words on the sweeps' mirror-speed factors (their
    index entries' `sweep_speed`; none: nothing)."""
    f = [e["sweep_speed"] for e in entries if "sweep_speed" in e]
    if not f:
        return ""
    lo, hi = 100 * (min(f) - 1), 100 * (max(f) - 1)
    return f"; mirror speed per sweep {lo:+.2f} to {hi:+.2f} %"


def cmd_evaluate(args):
    from ._base import evaluate, per_label_table
    from ._io import load_cube

    est = load_cube(args.cube)
    ref = load_cube(args.truth)
    e_shape, r_shape = est["cube"].shape, ref["cube"].shape
    if e_shape[:2] != r_shape[:2]:
        raise ValueError(f"cube {e_shape} and truth {r_shape} differ in shape")
    for name, data in ((args.cube, est), (args.truth, ref)):
        bad = int(np.count_nonzero(~np.isfinite(data["cube"])))
        if bad:  # the metrics would be NaN or meaningless
            raise ValueError(f"{name} holds {bad} NaN/inf value(s): metrics undefined")
    e_wl, r_wl = est["wavelengths_nm"], ref["wavelengths_nm"]
    if e_wl.shape != r_wl.shape or not np.allclose(e_wl, r_wl):
        if not args.resample:
            raise ValueError(
                f"cube ({e_wl.size} channels) and truth ({r_wl.size}) have different "
                "wavelengths_nm; --resample interpolates the cube onto the truth's"
            )
        from ._base import resample_matrix

        w = resample_matrix(e_wl, r_wl, name=f"cube {args.cube}")
        est = {**est, "cube": np.asarray(est["cube"], np.float64) @ w.T}
        print(
            f"evhsi evaluate: cube resampled from {e_wl.size} to {r_wl.size} channels "
            "(linear between channel centres)",
            file=sys.stderr,
        )
    res = evaluate(est["cube"], ref["cube"])
    if args.json:
        print(json.dumps(res))
        return 0
    print(
        f"SAM  {res['sam_deg']:.3f} deg   PSNR {res['psnr_db']:.2f} dB (peak 1)   "
        f"SSIM {res['ssim']:.4f}   RMS {res['rms']:.4f}"
    )
    if "labels" in ref:
        names = [str(v) for v in ref.get("names", [])]
        print(f"{'patch':28s} {'px':>6s} {'SAM deg':>8s} {'RMS':>7s} {'PSNR dB':>8s}")
        for row in per_label_table(est["cube"], ref["cube"], ref["labels"], names):
            print(
                f"{row['name'][:28]:28s} {row['pixels']:6d} {row['sam_deg']:8.2f} "
                f"{row['rms']:7.4f} {row['psnr_db']:8.2f}"
            )
    return 0


def cmd_convert(args):
    from ._io import DecodeReport, convert_events

    kind = _file_kind(args.src)
    if kind != "events":
        return _convert_cubes(args, kind)
    if args.sweep is not None:
        raise ValueError("--sweep applies to a per-sweep folder or video store")
    check_outputs({"IN": args.src}, {"OUT": args.dst})
    report = convert_events(args.src, args.dst, strict=args.strict)
    _problems(args, args.src, _decode_problems(report))
    skipped = {k: report[k] for k in DecodeReport.DEFECTS if report.get(k)}
    print(
        f"wrote {args.dst}"
        + (f" (skipped while decoding: {skipped})" if skipped else "")
    )
    return 0


def _file_kind(path) -> str:
    """What `convert` was given: "events", "cube" or "sweeps" (a per-sweep folder or
    video store), by extension and, for `.npz`, by its keys."""
    from ._video import holds_video

    p = Path(path)
    suffix = p.suffix.lower()
    if (p / "index.json").is_file() or holds_video(p):
        return "sweeps"
    if suffix in (".hdr", ".img", ".zarr"):
        return "cube"
    if suffix == ".npz" and p.is_file():
        try:
            import zipfile

            with zipfile.ZipFile(p) as z:
                names = set(z.namelist())
        except (OSError, zipfile.BadZipFile):
            return "events"  # the events reader names the problem
        return "cube" if "cube.npy" in names else "events"
    return "events"


def _convert_cubes(args, kind: str) -> int:
    from ._io import load_cube, save_cube
    from ._video import convert_sweeps, is_video_store, iter_sweep_cubes

    if kind == "sweeps" and args.sweep is None:
        if not is_video_store(args.dst):
            raise ValueError(
                "a per-sweep folder or store converts to a video store (OUT.zarr), "
                "or one sweep of it to a cube with --sweep K"
            )
        check_outputs({"IN": args.src}, {"OUT": args.dst})
        n = convert_sweeps(args.src, args.dst)
        print(f"wrote {args.dst} ({n} sweeps)")
        return 0
    out = _out_path(args.dst, CUBE_SUFFIXES, "OUT")
    check_outputs({"IN": args.src}, _cube_outputs(out, "OUT"))
    if kind == "sweeps":
        found = None
        for entry, data in iter_sweep_cubes(args.src):
            if entry["sweep"] == args.sweep:
                found = data
                break
        if found is None:
            raise ValueError(f"{args.src} holds no finished sweep {args.sweep}")
        data = found
    else:
        if args.sweep is not None:
            raise ValueError("--sweep applies to a per-sweep folder or video store")
        data = load_cube(args.src)
    extra = {k: v for k, v in data.items() if k not in ("cube", "wavelengths_nm")}
    save_cube(out, data["cube"], data["wavelengths_nm"], **extra)
    print(f"wrote {out}")
    return 0


def cmd_calibrate(args):
    from ._calibrate import calibrate, save_calibration
    from ._model import Calibration, load_scene

    out = _out_path(args.out, (".json",), "--out")
    chart_file = args.chart if str(args.chart).endswith(".npz") else None
    check_outputs(
        {"EVENTS": args.events, "--init": args.init, "--chart": chart_file},
        {"--out": out, "the maps file": Calibration.maps_path(out)},
    )
    init = _load_rig(args.init)
    events = _read_events(args, args.events)
    if len(events) == 0:
        raise ValueError(f"{args.events} holds no events")
    size = (events.height, events.width)
    chart = load_scene(
        args.chart, size if not str(args.chart).endswith(".npz") else None
    )
    if args.max_steps < 1:
        raise ValueError(f"--max-steps must be >= 1, got {args.max_steps}")
    res = calibrate(
        events,
        chart,
        init,
        per_pixel=not args.global_only,
        rows_per_label=args.rows_per_patch,
        t_start_us=args.t_start_us,
        max_steps=args.max_steps,
        fit_photoreceptor=not args.fixed_photoreceptor,
        fit_band={"auto": None, "fit": True, "keep": False}[args.band],
    )
    rig = res.rig
    cfg = save_calibration(
        out,
        res,
        comment=f"evhsi calibrate {Path(args.events).name} --chart {args.chart}",
    )
    print(f"{'parameter':18s} {'initial':>12s} {'fitted':>12s}")
    for k in ("threshold_on", "threshold_off", "beta_nm_per_rad", "baseline_rel"):
        print(f"{k:18s} {float(getattr(init, k)):12.5g} {float(getattr(rig, k)):12.5g}")
    offs = np.asarray(rig.column_offsets_us)
    d0 = np.asarray(init.column_offsets(events.width))
    print(
        f"{'column offsets':18s} {'':>12s} {events.width} columns, {offs.min():.1f} to "
        f"{offs.max():.1f} µs (RMS change {np.sqrt(np.mean((offs - d0) ** 2)):.1f} µs)"
    )
    if res.threshold_on_map is not None:
        print(
            f"{'per-pixel maps':18s} {'':>12s} ON sd {res.threshold_on_map.std():.4f}, "
            f"OFF sd {res.threshold_off_map.std():.4f} -> {cfg['threshold_map']}"
        )
    fx = rig.effects.floats()
    print(
        f"{'sensor noise':18s} {'':>12s} per-crossing threshold "
        f"{fx.threshold_noise:.4f} log, timestamp jitter {fx.timestamp_jitter_us:.2f} "
        f"µs, background {rig.noise_rate_hz:.2f} Hz/px, "
        f"{int(res.hot_pixels.sum())} hot pixel(s), {res.outlier_pixels} chart "
        "pixel(s) dropped as outliers"
    )
    how = "fitted" if res.photoreceptor_fitted else "kept from --init"
    print(
        f"{'photoreceptor':18s} {'':>12s} "
        + (
            f"cut-off {fx.photoreceptor_hz:,.0f} Hz at a white pixel ({how})"
            if fx.photoreceptor_hz > 0
            else f"no low-pass ({how})"
        )
    )
    print(f"{'mirror speed':18s} {'':>12s} {res.sweep_speed_note}")
    if rig.band_profile is None:
        band = f"Gaussian, FWHM {float(rig.fwhm_nm):.2f} nm (kept from --init" + (
            ": its fit did not converge)" if res.band_unresolved else ")"
        )
    else:
        off, val = (np.asarray(v, np.float64) for v in rig.band_profile)
        above = off[val >= 0.5]
        band = (
            f"{'fitted' if res.band_fitted else 'kept from --init'}"
            f"{' (its fit did not converge)' if res.band_unresolved else ''}: FWHM "
            f"{above[-1] - above[0]:.2f} nm, peak at {off[np.argmax(val)]:+.2f} nm"
        )
    print(f"{'band profile':18s} {'':>12s} {band}")
    print(cfg["comment"])
    print(f"wrote {out}")
    return 0


def cmd_view(args):
    from ._video import CubeSource, make_server

    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in [0, 65535], got {args.port}")
    source = CubeSource(args.cube, truth=args.truth)
    try:
        server = make_server(source, args.port)
    except OSError as err:
        raise ValueError(f"cannot listen on 127.0.0.1:{args.port} ({err.strerror})") from None
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    print(
        f"serving {args.cube} at {url} (Ctrl-C to stop; from another machine: "
        f"ssh -L {server.server_address[1]}:127.0.0.1:{server.server_address[1]} HOST)",
        flush=True,
    )
    if args.open:
        import webbrowser

        webbrowser.open(url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0


def cmd_demo(args):
    from ._demo import run_demo

    run_demo(Path(args.out), size=args.size, quiet=args.quiet)
    return 0


# --- parser ---------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    from ._model import Rig

    top = _Parser(
        prog="evhsi",
        description="Event-based active hyperspectral imaging: simulate, reconstruct, "
        "calibrate, evaluate.\n" + UNITS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    top.add_argument(
        "--float64", action="store_true", help="compute in float64 (default float32)"
    )
    top.add_argument(
        "--distributed",
        action="store_true",
        help="join a multi-host run (jax.distributed; EVHSI_COORDINATOR=host:port, "
        "EVHSI_NUM_PROCESSES, EVHSI_PROCESS_ID, or SLURM/MPI auto-detection)",
    )
    sub = top.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    p = sub.add_parser(
        "simulate",
        help="simulate events of a scene under the sweeping rainbow",
        description="Simulate the event camera watching a scene for N sweeps.\n"
        "Built-in scenes: colorchecker, gray-chart, rainbow, metamers; or a scene .npz "
        "with `reflectance` (H, W, L) in [0, 1] and `wavelengths_nm` (L,).\n" + UNITS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--scene", required=True, help="built-in scene name or scene .npz")
    p.add_argument(
        "--out",
        required=True,
        metavar="EVENTS",
        help="events file: .npz (x, y, p, t_us [µs], width, height) or .raw "
        "(Prophesee EVT 3.0)",
    )
    p.add_argument(
        "--truth",
        metavar="TRUTH",
        help="also write the reflectance on the rig's channel grid (cube file: .npz, "
        ".hdr ENVI or .zarr)",
    )
    _add_rig(p)
    p.add_argument("--sweeps", type=int, default=1, help="number of sweeps (default 1)")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="PRNG seed for threshold mismatch and noise (default: rig seed)",
    )
    p.add_argument(
        "--size",
        metavar="HxW",
        help="image size in pixels for built-in scenes (e.g. 96x144)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser(
        "rig",
        help="print the fully resolved rig as JSON",
        description="Print every rig key, defaults filled in, with column_offsets_us "
        "(µs) for the sensor width.\n\nkeys:\n" + Rig.describe_keys(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_rig(p)
    p.add_argument("--size", metavar="HxW", help="sensor size (default 720x1280)")
    p.set_defaults(func=cmd_rig)

    p = sub.add_parser(
        "render",
        help="render a cube to an sRGB PNG (CIE 1931, D65)",
        description="Render a reflectance cube file to sRGB through the CIE 1931 2° "
        "observer under D65 (colour-science).",
    )
    p.add_argument("cube", metavar="CUBE", help="cube file: .npz, .hdr (ENVI) or .zarr")
    p.add_argument("--out", required=True, metavar="PNG")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser(
        "info",
        help="summarise an events file (.npz, .raw EVT 2.0/3.0)",
        description="Geometry, event count, duration (µs), rate (events/s), polarity "
        "balance, triggers, bytes per event.",
    )
    p.add_argument("events", metavar="EVENTS")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    _add_strict(p)
    p.set_defaults(func=cmd_info)

    from ._reconstruct import SOLVERS, ProblemConfig

    p = sub.add_parser(
        "reconstruct",
        help="reconstruct a hyperspectral cube from events",
        description="Solve one box-constrained QP per pixel (paper Eq. 20) and write "
        "a cube file: `cube` (H, W, M) float32 reflectance, `wavelengths_nm` (M,) "
        "channel centres in nm.\n" + UNITS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("events", metavar="EVENTS", help="events file (.npz or .raw)")
    p.add_argument(
        "--calib",
        metavar="CALIB.json",
        required=True,
        help="calibration / rig JSON (keys left out take default values)",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="CUBE|DIR",
        help="cube file by extension: .npz, .hdr (ENVI: .hdr + .img) or .zarr; with "
        "--per-sweep a folder (created) of per-sweep cube files, or a video store "
        "VIDEO.zarr (Zarr: reflectance over time, wavelength and time coordinates)",
    )
    p.add_argument("--preview", metavar="PNG", help="also write an sRGB preview")
    p.add_argument(
        "--per-sweep",
        action="store_true",
        help="one cube per sweep (video): stream the file with bounded memory into "
        "DIR/sweep_NNNNNN.npz + DIR/index.json + DIR/preview.gif; rerunning resumes",
    )
    p.add_argument(
        "--max-sweeps", type=int, default=None, help="per-sweep: stop after N sweeps"
    )
    p.add_argument(
        "--low-events",
        type=float,
        default=0.5,
        metavar="REL",
        help="per-sweep: flag sweeps with fewer events than REL x the median (0.5)",
    )
    p.add_argument(
        "--restart",
        action="store_true",
        help="per-sweep: discard what DIR holds instead of resuming",
    )
    p.add_argument(
        "--follow",
        action="store_true",
        help="per-sweep, .raw: the file is still being written (live capture); "
        "reconstruct each sweep as soon as it is complete, stop when the file has "
        "not grown for --idle-timeout seconds or on SIGINT/SIGTERM (then the sweeps "
        "read so far are finished; a second signal aborts)",
    )
    p.add_argument(
        "--idle-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="with --follow: seconds without new data that end the recording (10)",
    )
    p.add_argument(
        "--channels",
        type=int,
        default=None,
        metavar="N",
        help="recover N channels over the calibration's range instead of its own "
        "(the cube holds N; its wavelengths_nm say where): fewer are faster, at the "
        "price of detail narrower than a channel (README, Channels)",
    )
    p.add_argument(
        "--roi",
        metavar="x0,y0,x1,y1",
        help="reconstruct only this region (pixels, half-open; e.g. 0,0,320,180): "
        "faster, for live views",
    )
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        metavar="N",
        help="shard pixels over N devices (0: all, every host's; on a CPU, N > 1 "
        "splits it into N XLA host devices: --devices 2 uses both cores of a "
        "2-core machine); default: every core of a CPU (at most 8) for a whole "
        "recording, one device with --per-sweep",
    )
    p.add_argument(
        "--backend",
        default="auto",
        choices=["auto", "jax", "fused", "cuda"],
        help="auto (default): the fused CPU kernel (each pixel's system formed from "
        "band segments and solved in float64 on every core) where it applies — "
        "active-set solver, solve on a CPU — else the JAX kernels, and on a CUDA "
        "GPU the cuda kernel for captures of at least 2^19 pixel-sweeps; cuda: "
        "JAX's rows, each pixel's Gram and box QP by a CUDA kernel on the GPU's "
        "chip (numba's CUDA target, kernel cached on disk; ~1 s of numba start "
        "per process, faster per sweep); jax, fused or cuda to choose (fused and "
        "cuda refuse what they cannot run)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="N",
        help="worker threads of the fused backend (default: every usable core)",
    )
    p.add_argument(
        "--solver",
        default="auto",
        choices=["auto", *SOLVERS],
        help="QP solver (default auto: the fastest at the reference's accuracy)",
    )
    p.add_argument(
        "--t-start-us",
        type=int,
        default=None,
        help="start of the first sweep in µs (default: first trigger, else 0)",
    )
    p.add_argument(
        "--deblur",
        choices=sorted(_DEBLUR),
        default="auto",
        help="undo the optics' blur (the calibration's psf_sigma_px, pixels) by "
        "Wiener deconvolution per channel: auto (default) when the calibration "
        "measured one, on, off",
    )
    pc = ProblemConfig()
    p.add_argument(
        "--photoreceptor-passes",
        type=int,
        default=None,
        metavar="N",
        help="at most N Gauss-Newton passes of the photoreceptor model when the "
        "calibration has a photoreceptor cut-off, or threshold noise or jitter without "
        "one (then of an instantaneous photoreceptor: rows in log units) (default "
        f"{pc.lowpass_passes}; 0: the first solve alone); a pixel stops once a pass "
        f"changed its spectrum by <= {pc.lowpass_tol * 100:g}%%, so a fast "
        "photoreceptor costs about one pass and a slow one takes more (README, Real "
        "sensors)",
    )
    p.add_argument(
        "--stray-z",
        type=float,
        default=None,
        metavar="Z",
        help="when the calibration measured background activity, a pixel whose worst "
        "event row is left more than Z standard deviations from its answer is solved "
        "again without each of its events in turn (and a second time for a second "
        "one), and those that explain it are removed as stray background events "
        f"(default {pc.stray_z:g}; 0: never; "
        "README, Real sensors)",
    )
    p.add_argument(
        "--sweep-speed",
        default="auto",
        metavar="auto|off|F[,F...]",
        help="each sweep's mirror speed relative to the calibration's: auto (default) "
        "measures each sweep's from the recording (with --per-sweep each sweep "
        "alone; a mirror whose speed varies by 0.2%% from sweep to sweep otherwise "
        "costs a sweep ~1.3° SAM; README, Real sensors); off keeps the "
        "calibration's; or the factors, one per sweep used (e.g. 1.002,0.999); the "
        "summary lists the factors used (the --per-sweep index: each sweep's "
        "sweep_speed)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_strict(p)
    p.set_defaults(func=cmd_reconstruct)

    p = sub.add_parser(
        "evaluate",
        help="compare a cube with the truth (SAM, PSNR, SSIM, RMS)",
        description="SAM: mean over pixels of the angle (degrees) between estimated "
        "and true spectra. MSE over the whole cube; PSNR = 10 log10(1/MSE) dB "
        "(reflectance peak 1); RMS = sqrt(MSE); SSIM of each channel image "
        "(Gaussian window σ = 1.5), averaged over channels.",
    )
    p.add_argument("cube", metavar="CUBE", help="cube file: .npz, .hdr (ENVI) or .zarr")
    p.add_argument("--truth", metavar="TRUTH", required=True, help="cube file, ditto")
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object {sam_deg, psnr_db, ssim, rms}",
    )
    p.add_argument(
        "--resample",
        action="store_true",
        help="where the cube's wavelengths_nm differ from the truth's (reconstruct "
        "--channels), interpolate the cube linearly onto the truth's channel centres "
        "(said on stderr) instead of refusing",
    )
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "convert",
        help="convert events (.raw/.npz), cubes (.npz/.hdr/.zarr) or per-sweep video",
        description="Convert by extension. Events: reads .raw (EVT 2.0 or 3.0) or "
        ".npz, writes .raw (EVT 3.0) or .npz. Cubes: any of .npz, .hdr (ENVI, with "
        ".img beside it) and .zarr to any other. Per-sweep video: a --per-sweep "
        "folder to a video store OUT.zarr, or one sweep (--sweep K) of a folder or "
        "store to a cube file.",
    )
    p.add_argument("src", metavar="IN")
    p.add_argument("dst", metavar="OUT")
    p.add_argument(
        "--sweep",
        type=int,
        default=None,
        metavar="K",
        help="from a per-sweep folder or video store: write sweep K as one cube",
    )
    _add_strict(p)
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser(
        "calibrate",
        help="fit thresholds, β, c and column offsets to a chart capture",
        description="Fit the rig jointly (optimistix Levenberg-Marquardt) to events of "
        "a chart of known reflectance: ON/OFF thresholds (log units), sweep coefficient "
        "β (nm/rad), constant light c (fraction of a white pixel's peak) and one time "
        "offset τx per column (µs); then per-pixel threshold maps, written to a sibling "
        "<out>_thresholds.npz named by the calibration file.\n" + UNITS,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "events", metavar="EVENTS", help="capture of the chart (.npz or .raw)"
    )
    p.add_argument(
        "--chart",
        default="gray-chart",
        help="built-in chart (gray-chart, colorchecker, ...) laid out on the "
        "sensor, or a scene .npz of the sensor's size",
    )
    p.add_argument("--out", required=True, metavar="CALIB.json")
    p.add_argument(
        "--init", metavar="RIG.json", help="initial rig (default: paper rig)"
    )
    p.add_argument(
        "--rows-per-patch",
        type=int,
        default=4,
        help="rows of each patch per column used in the global fit",
    )
    p.add_argument(
        "--global-only", action="store_true", help="skip the per-pixel threshold maps"
    )
    p.add_argument(
        "--fixed-photoreceptor",
        action="store_true",
        help="keep the photoreceptor cut-off of --init (photoreceptor_hz, Hz; 0 = "
        "none) instead of measuring it from the chart (the default: fitted jointly "
        "with the rest; a cut-off too fast to matter, above 500 kHz, counts as none)",
    )
    p.add_argument(
        "--band",
        choices=("auto", "fit", "keep"),
        default="auto",
        help="the band profile: fitted from the chart (a smooth correction of "
        "--init's band_profile, or of the Gaussian of its fwhm_nm), or kept as "
        "--init gives it; auto (default): fitted unless --init gives a band_profile",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=100,
        help="Levenberg–Marquardt step limit per stage; a fit that reaches it is "
        "refused (default 100)",
    )
    p.add_argument(
        "--t-start-us",
        type=int,
        default=None,
        help="start of the first sweep in µs (default: first trigger, else 0)",
    )
    _add_strict(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser(
        "view",
        help="look at a cube or per-sweep video in the browser (127.0.0.1 only)",
        description="Serve an interactive page on 127.0.0.1 (this machine only): the "
        "sRGB rendering or one channel (wavelength slider), click pixels to plot and "
        "compare their spectra (with the truth and SAM if --truth is given), and for "
        "a per-sweep folder or VIDEO.zarr a sweep timeline with play and 'follow the "
        "newest' (for a running --per-sweep --follow reconstruction). From a remote "
        "machine, tunnel the port over SSH instead of exposing it: "
        "`ssh -L PORT:127.0.0.1:PORT HOST`, then open http://127.0.0.1:PORT locally.",
    )
    p.add_argument("cube", metavar="CUBE|DIR", help="cube file, per-sweep folder or store")
    p.add_argument("--truth", metavar="TRUTH", help="truth cube to plot beside")
    p.add_argument(
        "--port",
        type=int,
        default=8765,
        help="port on 127.0.0.1 (default 8765; 0: any free one)",
    )
    p.add_argument("--open", action="store_true", help="open it in the web browser")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser(
        "demo",
        help="the main job on the built-in default scene (make demo)",
        description="Simulate the ColorChecker with the paper's rig and report.",
    )
    p.add_argument("--out", default="out/demo", help="output folder (created)")
    p.add_argument("--size", default="96x144", metavar="HxW", help="image size")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_demo)
    return top


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if hasattr(args, "devices"):
        _cpu_devices(args.devices)
    if args.float64:  # must happen before any array exists
        import jax

        jax.config.update("jax_enable_x64", True)
    if args.command in ("simulate", "reconstruct", "calibrate", "demo"):
        from ._base import enable_compilation_cache

        enable_compilation_cache()  # EVHSI_CACHE_DIR=off turns it off
    try:
        if args.distributed:
            from ._base import initialize_distributed

            initialize_distributed()
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # (a closed pipe shows here, not at the interpreter's exit)
        return code
    except KeyboardInterrupt:
        print("evhsi: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of stdout went away (`evhsi evaluate ... | head -1`): not an
        # error of the input. Stop quietly, with the shell's code for SIGPIPE; stdout
        # to /dev/null so that Python's own flush at exit does not complain.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (ValueError, OSError) as err:
        if os.environ.get("EVHSI_DEBUG"):
            raise
        msg = " ".join(str(err).split()) or type(err).__name__
        print(f"evhsi {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except MemoryError:  # sizes are checked up front; this is what slipped through
        if os.environ.get("EVHSI_DEBUG"):
            raise
        print(
            f"evhsi {args.command}: error: not enough memory for this input (make "
            "it smaller: fewer sweeps or a smaller image)",
            file=sys.stderr,
        )
        return 2
    except Exception as err:  # a bug, not a user mistake: still one line, say so
        if os.environ.get("EVHSI_DEBUG"):
            raise
        msg = " ".join(str(err).split())
        print(
            f"evhsi {args.command}: internal error ({type(err).__name__}: {msg}); "
            "rerun with EVHSI_DEBUG=1 for a traceback",
            file=sys.stderr,
        )
        return 3


if __name__ == "__main__":
    sys.exit(main())
