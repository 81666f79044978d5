"""Event-file throughput: our EVT 3.0 decoder/encoder against the PyPI peers.

Setup: three event layouts are generated (seeded) and written with our EVT 3.0 writer:

- `clustered` (>= 10 M events by default): rows of neighbouring columns firing in the
  same µs, rows drifting like moving edges — vector words carry most events;
- `scattered`: uniform random pixels, a few events per µs — one EVT_ADDR_X (and often a
  row and a TIME_LOW word) per event, the layout of the bundled Gen4.1 recording;
- `real`: the bundled Gen4.1 recording (`shared/data/evt3_sample.raw`), when present.

Each file is decoded by `evhsi_jax` with its compiled (numba) kernels — the default —
and with the vectorised NumPy reference (`EVHSI_NO_NUMBA=1`; default threads), by `evt3`
(Rust) and by `expelliarmus` (C); encoding (`write_evt3` to a file, atomic) is timed for
both `evhsi_jax` paths and `expelliarmus` (`.save`; `evt3` has no writer). Runs are
interleaved round-robin (the order rotating from round to round) and repeated; the table
reports the median (and best) wall time as Mev/s. Every decoder's output is checked
against the source events first (x, y, p; t too for ours and evt3), and both of our
writers must produce the same bytes. The numba kernels' one-time cost (compile on first
use with an empty cache; load from the on-disk cache) is measured separately, in fresh
processes. Machine: whatever runs it — the JSON records CPU count, load averages (at the
start and after each dataset), the busiest other processes, and versions.

usage: python experiments/bench_event_io.py [--events 10000000] [--repeats 5]
writes experiments/results/bench_event_io.json and .png
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

from evhsi_jax import EventStream
from evhsi_jax._base._numba import use_backend  # the benchmark compares the two paths
from evhsi_jax.io import EventReader, evt3_bytes, write_evt3

OURS, REFERENCE = "evhsi_jax (numba)", "evhsi_jax (NumPy)"

HERE = Path(__file__).resolve().parent
DATA = Path(os.environ.get("EVHSI_SHARED_DATA", HERE.parents[1] / "shared" / "data"))


def clustered(n: int, seed: int, width: int = 1280, height: int = 720) -> EventStream:
    """Rows of neighbouring columns in one µs (runs of 1..48, 75 % filled)."""
    rng = np.random.default_rng(seed)
    bursts = n // 5 + 1000
    length = np.clip(rng.geometric(1 / 8, bursts), 1, 48)
    t = np.cumsum(rng.poisson(0.5, bursts)) + 1000
    y = np.cumsum(rng.integers(-3, 4, bursts)) % height
    p = rng.integers(0, 2, bursts)
    x0 = rng.integers(0, width - 48, bursts)
    b = np.repeat(np.arange(bursts), length)
    off = np.arange(b.size) - np.repeat(np.cumsum(length) - length, length)
    keep = rng.random(b.size) < 0.75
    b, off = b[keep][:n], off[keep][:n]
    return EventStream(x0[b] + off, y[b], p[b], t[b], width, height)


def scattered(n: int, seed: int, width: int = 1280, height: int = 720) -> EventStream:
    """Uniform random pixels, about 3 events per µs."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, n // 3, n))
    return EventStream(
        rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n),
        t, width, height,
    )  # fmt: skip


def decoders() -> dict:
    import evt3
    import expelliarmus

    def reference(p):
        with use_backend("numpy"):
            return EventReader(p).read()

    def ours(p):
        with use_backend("numba"):
            return EventReader(p).read()

    return {
        OURS: ours,
        REFERENCE: reference,
        "evt3 (Rust)": lambda p: evt3.decode_file(str(p)),
        "expelliarmus (C)": lambda p: expelliarmus.Wizard(encoding="evt3").read(p),
    }


def columns(name: str, out) -> dict:
    """x, y, p, t of any decoder's result."""
    if name.startswith("evhsi_jax"):
        return dict(x=out.x, y=out.y, p=out.p, t=out.t_us)
    if name.startswith("evt3"):
        return dict(x=out.x, y=out.y, p=out.polarity, t=out.t.astype(np.int64))
    return dict(x=out["x"], y=out["y"], p=out["p"], t=out["t"])


def check(name: str, out, ev: EventStream) -> None:
    got = columns(name, out)
    for k, ref in (("x", ev.x), ("y", ev.y), ("p", ev.p)):
        if not np.array_equal(
            np.asarray(got[k]).astype(np.int64), ref.astype(np.int64)
        ):
            raise SystemExit(f"{name} decodes {k} differently: benchmark invalid")
    if not name.startswith("expelliarmus") and not np.array_equal(got["t"], ev.t_us):
        raise SystemExit(f"{name} decodes t differently: benchmark invalid")


def timed(fn, *args) -> tuple[float, float]:
    """Wall time and CPU time of this process (all threads) for one call."""
    t0, c0 = time.perf_counter(), time.process_time()
    fn(*args)
    return time.perf_counter() - t0, time.process_time() - c0


def bench(name: str, ev: EventStream, path: Path, repeats: int, workdir: Path) -> dict:
    import expelliarmus

    decs = decoders()
    for dname, fn in decs.items():
        check(dname, fn(path), ev)  # also warms caches and imports
    layout = {  # the record layout expelliarmus reads and writes
        "names": ["t", "x", "y", "p"],
        "formats": ["<i8", "<i2", "<i2", "u1"],
        "offsets": [0, 8, 10, 12],
        "itemsize": 16,
    }
    arr = np.zeros(len(ev), np.dtype(layout))
    arr["t"], arr["x"], arr["y"], arr["p"] = ev.t_us, ev.x, ev.y, ev.p
    wiz = expelliarmus.Wizard(encoding="evt3")

    def write(name: str, backend: str):
        with use_backend(backend):
            write_evt3(workdir / name, ev)

    encs = {
        OURS: lambda: write("enc_ours.raw", "numba"),
        REFERENCE: lambda: write("enc_ref.raw", "numpy"),
        "expelliarmus (C)": lambda: wiz.save(workdir / "enc_exp.raw", arr),
    }
    for fn in encs.values():
        fn()
    ours_bytes = (workdir / "enc_ours.raw").read_bytes()
    if ours_bytes != (workdir / "enc_ref.raw").read_bytes():
        raise SystemExit("the numba and NumPy writers differ: benchmark invalid")
    dec_t = {k: [] for k in decs}
    enc_t = {k: [] for k in encs}
    # Round-robin, so load changes hit everyone alike; the order rotates each round,
    # so no tool always runs right after the one that freed (or dirtied) most memory.
    dec_names, enc_names = list(decs), list(encs)
    for r in range(repeats):
        for k in dec_names[r % len(decs) :] + dec_names[: r % len(decs)]:
            dec_t[k].append(timed(decs[k], path))
        for k in enc_names[r % len(encs) :] + enc_names[: r % len(encs)]:
            enc_t[k].append(timed(encs[k]))
    n = len(ev)
    sizes = {
        k: (workdir / f).stat().st_size
        for k, f in ((OURS, "enc_ours.raw"), ("expelliarmus (C)", "enc_exp.raw"))
    }

    def rates(times: dict) -> dict:
        out = {}
        for k, v in times.items():
            wall = [w for w, _ in v]
            cpu = [c for _, c in v]
            out[k] = {
                "median_s": statistics.median(wall),
                "best_s": min(wall),
                "median_mev_s": n / statistics.median(wall) / 1e6,
                "best_mev_s": n / min(wall) / 1e6,
                # Throughput per CPU-second: less sensitive to other load on the
                # machine (but it hides what a second thread gains in wall time).
                "median_cpu_s": statistics.median(cpu),
                "mev_per_cpu_s": n / max(statistics.median(cpu), 1e-9) / 1e6,
            }
        return out

    return {
        "dataset": name,
        "events": n,
        "load_average_after": os.getloadavg(),
        "file_bytes": path.stat().st_size,
        "bits_per_event": 8 * evt3_bytes(ev) / max(n, 1),
        "encoded_bytes": sizes,
        "decode": rates(dec_t),
        "encode": rates(enc_t),
    }


def table(results: list[dict]) -> str:
    lines = [
        "| dataset | events | EVT3 bits/event | tool | decode Mev/s wall: median "
        "(best) | decode Mev per CPU-s | encode Mev/s wall: median (best) |",
        "|---|---:|---:|---|---:|---:|---:|",
    ]
    for r in results:
        for tool, d in r["decode"].items():
            e = r["encode"].get(tool)
            enc = f"{e['median_mev_s']:.1f} ({e['best_mev_s']:.1f})" if e else "—"
            lines.append(
                f"| {r['dataset']} | {r['events']:,} | {r['bits_per_event']:.1f} | {tool} "
                f"| {d['median_mev_s']:.1f} ({d['best_mev_s']:.1f}) "
                f"| {d['mev_per_cpu_s']:.1f} | {enc} |"
            )
    return "\n".join(lines)


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 3.8))
    for ax, what in zip(axes, ("decode", "encode")):
        tools = list(results[0][what])
        width = 0.8 / len(tools)
        for i, tool in enumerate(tools):
            vals = [r[what][tool]["median_mev_s"] for r in results]
            ax.bar(np.arange(len(results)) + i * width, vals, width, label=tool)
        ax.set_xticks(np.arange(len(results)) + 0.4 - width / 2)
        ax.set_xticklabels([r["dataset"] for r in results])
        ax.set_ylabel(f"{what} throughput (Mev/s, median)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


_FIRST_USE = """
import time
t0 = time.perf_counter()
import numpy as np
from evhsi_jax import EventStream
from evhsi_jax._io import EventReader, write_evt3
ev = EventStream(np.arange(3), np.zeros(3), np.ones(3), np.arange(3) * 5000, 8, 8,
                 trigger_t_us=np.array([1]), trigger_p=np.array([1]),
                 trigger_id=np.array([0]))
t1 = time.perf_counter()
write_evt3({path!r}, ev)
EventReader({path!r}).read()
EventReader({path!r}, chunk_bytes=4).read_window(0, 10)  # per-chunk kernels
t2 = time.perf_counter()
print(t2 - t1)
"""


def other_load() -> list[str]:
    """The busiest other processes now (`ps`), to report what shared the machine."""
    try:
        ps = subprocess.run(
            ["ps", "-eo", "pcpu,pid,args", "--sort=-pcpu"],
            capture_output=True, text=True, check=True,
        ).stdout.splitlines()[1:]  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return []
    own = str(os.getpid())
    rows = [r.strip()[:100] for r in ps if r.split()[1] != own]
    return [r for r in rows if float(r.split()[0]) >= 5.0][:5]


def first_use(workdir: Path) -> dict:
    """Seconds the first write + read + window index of a tiny EVT 3.0 file take in a
    fresh process (numba: compiling every kernel, or loading them from the cache)."""
    out = {}
    code = _FIRST_USE.format(path=str(workdir / "tiny.raw"))
    cold = workdir / "numba_cache"
    for label, env in (
        ("numba, empty cache (compile)", {"NUMBA_CACHE_DIR": str(cold)}),
        ("numba, warm cache (load)", {"NUMBA_CACHE_DIR": str(cold)}),
        ("NumPy", {"EVHSI_NO_NUMBA": "1"}),
    ):
        run = subprocess.run(
            [sys.executable, "-c", code], env={**os.environ, **env},
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        out[label] = float(run.stdout.split()[-1])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=10_000_000, help="clustered events")
    ap.add_argument("--scattered", type=int, default=3_000_000, help="scattered events")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()
    busy0 = other_load()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        startup = first_use(work)
        print(f"first use (s): {startup}", flush=True)
        sets = [
            ("clustered", clustered(args.events, args.seed)),
            ("scattered", scattered(args.scattered, args.seed + 1)),
        ]
        for name, ev in sets:
            path = work / f"{name}.raw"
            write_evt3(path, ev)
            results.append(bench(name, ev, path, args.repeats, work))
            print(f"done: {name}", flush=True)
        real = DATA / "evt3_sample.raw"
        if real.is_file():
            ev = EventReader(real).read()
            results.append(bench("real Gen4.1", ev, real, 5 * args.repeats, work))
    meta = {
        "command": "python experiments/bench_event_io.py "
        + f"--events {args.events} --scattered {args.scattered} --repeats {args.repeats}",
        "machine": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_average_start": load0,
        "load_average_end": os.getloadavg(),
        "other_processes_start": busy0,
        "other_processes_end": other_load(),
        "first_use_s": startup,
        "versions": {
            k: version(k)
            for k in ("numpy", "numba", "evt3", "expelliarmus", "evhsi_jax")
        },
    }
    (args.out / "bench_event_io.json").write_text(
        json.dumps({"meta": meta, "results": results}, indent=1)
    )
    plot(results, args.out / "bench_event_io.png")
    print(table(results))
    print(f"\ncpus {meta['cpus']}, load average {load0} -> {meta['load_average_end']}")
    print(f"first use of the file layer in a fresh process (s): {startup}")
    print("other processes (start, end):", busy0, meta["other_processes_end"])


if __name__ == "__main__":
    main()
