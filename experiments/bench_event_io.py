"""Event-file throughput: our EVT 3.0 decoder/encoder against the PyPI peers.

Setup: three event layouts are generated (seeded) and written with our EVT 3.0 writer:

- `clustered` (>= 10 M events by default): rows of neighbouring columns firing in the
  same µs, rows drifting like moving edges — vector words carry most events;
- `scattered`: uniform random pixels, a few events per µs — one EVT_ADDR_X (and often a
  row and a TIME_LOW word) per event, the layout of the bundled Gen4.1 recording;
- `real`: the bundled Gen4.1 recording (`shared/data/evt3_sample.raw`), when present.

Each file is decoded by `evhsi_jax` (default settings: two threads for large files;
and with `workers=1`), by `evt3` (Rust) and by `expelliarmus` (C); encoding is timed for
`evhsi_jax` and `expelliarmus` (`evt3` has no writer). Runs are interleaved round-robin
and repeated; the table reports the median (and best) wall time as Mev/s. Every decoder's
output is checked against the source events first (x, y, p; t too for ours and evt3).
Machine: whatever runs it — the JSON records CPU count, load average and versions.

usage: python experiments/bench_event_io.py [--events 10000000] [--repeats 5]
writes experiments/results/bench_event_io.json and .png
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np

try:  # the public API (re-exported at the top level once wired)
    from evhsi_jax import EventReader, EventStream, evt3_bytes, write_evt3
except ImportError:  # pragma: no cover - before the top-level re-export exists
    from evhsi_jax import EventStream
    from evhsi_jax._io import EventReader, evt3_bytes, write_evt3

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

    return {
        "evhsi_jax": lambda p: EventReader(p).read(),
        "evhsi_jax (1 thread)": lambda p: EventReader(p, workers=1).read(),
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
    encs = {
        "evhsi_jax": lambda: write_evt3(workdir / "enc_ours.raw", ev),
        "expelliarmus (C)": lambda: wiz.save(workdir / "enc_exp.raw", arr),
    }
    dec_t = {k: [] for k in decs}
    enc_t = {k: [] for k in encs}
    for _ in range(repeats):  # round-robin, so load changes hit everyone alike
        for k, fn in decs.items():
            dec_t[k].append(timed(fn, path))
        for k, fn in encs.items():
            enc_t[k].append(timed(fn))
    n = len(ev)
    sizes = {
        k: (workdir / f).stat().st_size
        for k, f in (("evhsi_jax", "enc_ours.raw"), ("expelliarmus (C)", "enc_exp.raw"))
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

    tools = list(results[0]["decode"])
    fig, ax = plt.subplots(figsize=(8, 3.5))
    width = 0.8 / len(tools)
    for i, tool in enumerate(tools):
        vals = [r["decode"][tool]["median_mev_s"] for r in results]
        ax.bar(np.arange(len(results)) + i * width, vals, width, label=tool)
    ax.set_xticks(np.arange(len(results)) + 0.4 - width / 2)
    ax.set_xticklabels([r["dataset"] for r in results])
    ax.set_ylabel("decode throughput (Mev/s, median)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


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
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
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
        "versions": {
            k: version(k) for k in ("numpy", "evt3", "expelliarmus", "evhsi_jax")
        },
    }
    (args.out / "bench_event_io.json").write_text(
        json.dumps({"meta": meta, "results": results}, indent=1)
    )
    plot(results, args.out / "bench_event_io.png")
    print(table(results))
    print(f"\ncpus {meta['cpus']}, load average {load0} -> {meta['load_average_end']}")


if __name__ == "__main__":
    main()
