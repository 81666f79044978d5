"""Where the fused CPU kernel spends its time, per compiled function (Linux `perf`).

Switching stages of the kernel off one at a time also changes what is left (a missing
row narrows Q's envelope, so the factorisation gets cheaper too); a sampling profile
does not. numba's machine code has no symbols `perf` can see, so the script writes a
perf map (`/tmp/perf-<pid>.map`: start, size and name of each function of the kernel's
compiled module, from numba's code library and the symbol table of its object code),
which `perf report` reads.

Setup: one sweep of the ColorChecker at `--size` (default 96×144), paper rig with the
`--sensor` preset (as `bench_kernel_ab.py`), the true rig as the calibration; the
kernel compiled afresh into a temporary numba cache (the compiled module must be built
in this process for its function addresses), one warm-up call, then `--repeats` calls
on one thread under `perf record -e cpu-clock`. Printed and written: each kernel
function's share of the kernel's samples (functions inlined by numba or LLVM count as
their caller), µs per pixel of the profiled calls, the float32 matmul GFLOP/s.

`--annotate FUNC` (e.g. `solve_pixels`): also where inside that function the samples
fall, by instruction — its machine code is copied out of the process and
disassembled (`objdump`), each instruction with its share of the function's samples
(written to `--annotate-out`, default `/tmp/profile_kernel_<FUNC>.txt`), and the ten
busiest 64-byte windows printed. A timer sample lands an instruction or two after
the one that stalled. (This found the AVX-512 scatters of the rows' clearing loops,
2026-11-27.)

    python experiments/profile_kernel.py [--sensor ideal|noise|realistic]
        [--size 96x144] [--repeats 8] [--out PATH] [--annotate FUNC]
        [--annotate-out PATH]

Needs `perf` (Debian: linux-perf) and permission to sample the process
(`kernel.perf_event_paranoid` ≤ 2); exits with status 2 and a one-line reason
otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _short(mangled: str) -> str:
    """The function's own name out of numba's Itanium-mangled symbol."""
    m = re.match(r"_ZN(.*)", mangled)
    if not m:
        return mangled
    rest, parts = m.group(1), []
    while True:
        d = re.match(r"(\d+)", rest)
        if not d:
            break
        n = int(d.group(1))
        start = len(d.group(1))
        parts.append(rest[start : start + n])
        rest = rest[start + n :]
    return parts[-1] if parts else mangled


def _elf_sizes(obj: bytes) -> dict[str, int]:
    """Size of each function symbol of an ELF64 object file (numba's compiled module):
    the perf map's ranges. Taken up to the next function's start instead, a function
    followed by a gap in memory had claimed the samples of whatever code lay in the
    gap (e.g. the simulator's XLA code: ~5–15 % "_lane_clear")."""
    shoff = int.from_bytes(obj[0x28:0x30], "little")
    shentsize = int.from_bytes(obj[0x3A:0x3C], "little")
    shnum = int.from_bytes(obj[0x3C:0x3E], "little")
    secs = []
    for i in range(shnum):
        h = obj[shoff + i * shentsize : shoff + (i + 1) * shentsize]
        # (type, offset, size, link)
        fields = ((4, 8), (24, 32), (32, 40), (40, 44))
        secs.append(tuple(int.from_bytes(h[a:b], "little") for a, b in fields))
    sizes = {}
    for typ, off, size, link in secs:
        if typ != 2:  # SHT_SYMTAB
            continue
        str_off = secs[link][1]
        for e in range(off, off + size, 24):
            name_at = int.from_bytes(obj[e : e + 4], "little")
            if obj[e + 4] & 0xF != 2:  # STT_FUNC
                continue
            end = obj.index(b"\0", str_off + name_at)
            name = obj[str_off + name_at : end].decode()
            sizes[name] = int.from_bytes(obj[e + 16 : e + 24], "little")
    return sizes


def child(args):
    from _kernel_setup import fused_inputs

    from evhsi_jax._reconstruct import _fused

    setup = fused_inputs(args.sensor, args.size)
    sel = setup.sel

    def solve():
        return _fused.solve_fused(setup.prob, sel, *setup.args, threads=1)

    solve()  # compiles into the (empty) temporary cache
    from evhsi_jax._reconstruct import _fused_jit as jit

    disp = jit.solve_pixels
    lib = disp.overloads[disp.signatures[0]].library
    names = set(re.findall(r'^define [^@]*@"?([^"( ]+)"?\(', lib.get_llvm_str(), re.M))
    starts_ = sorted(
        (lib.get_pointer_to_function(n), n) for n in names
        if lib.get_pointer_to_function(n)
    )  # fmt: skip
    sizes = _elf_sizes(lib._get_compiled_object())
    if args.annotate:  # the function's machine code, for the disassembly
        import ctypes

        found = [
            (sizes[n], lib.get_pointer_to_function(n)) for _, n in starts_
            if _short(n) == args.annotate and n in sizes
        ]  # fmt: skip
        if not found:
            Path(args.child).write_text(json.dumps({"error": args.annotate}))
            return
        size, addr = max(found)  # (the function itself, not its Python wrapper)
        Path(args.child + ".bin").write_bytes(ctypes.string_at(addr, size))
        Path(args.child + ".at").write_text(f"{addr} {size}")
    with open(f"/tmp/perf-{os.getpid()}.map", "w") as f:
        for (a, n), (b, _) in zip(starts_, starts_[1:] + [(starts_[-1][0] + 4096, "")]):
            f.write(f"{a:x} {min(b - a, sizes.get(n, b - a)):x} "
                    f"evhsi_kernel:{_short(n)}\n")  # fmt: skip
    t = time.perf_counter()
    for _ in range(args.repeats):
        solve()
    us = 1e6 * (time.perf_counter() - t) / args.repeats / sel.size
    Path(args.child).write_text(
        json.dumps({"us_per_px": us, "pixels": int(sel.size), "pid": os.getpid()})
    )


def annotate(perf: str, data: Path, res: Path, args) -> None:
    """Samples per instruction of the function `args.annotate` (see the module
    docstring): written whole, its ten busiest 64-byte windows printed."""
    from collections import Counter

    objdump = shutil.which("objdump")
    if objdump is None:
        print("profile_kernel: `objdump` not found (Debian: apt install binutils)")
        sys.exit(2)
    addr, size = (int(v) for v in Path(str(res) + ".at").read_text().split())
    ips = subprocess.run(
        [perf, "script", "-i", str(data), "-F", "ip"], capture_output=True, text=True
    ).stdout.split()  # fmt: skip
    hits = Counter(v - addr for v in (int(x, 16) for x in ips) if 0 <= v - addr < size)
    total = max(sum(hits.values()), 1)
    dis = subprocess.run(
        [objdump, "-D", "-b", "binary", "-m", "i386:x86-64", str(res) + ".bin"],
        capture_output=True, text=True,
    ).stdout  # fmt: skip
    lines, windows = [], Counter()
    for line in dis.splitlines():
        m = re.match(r"\s*([0-9a-f]+):\s+(?:[0-9a-f]{2} )+\s*(.*)", line)
        if m:
            off = int(m.group(1), 16)
            share = hits.get(off, 0) / total
            windows[off // 64] += share
            lines.append(f"{100 * share:6.2f} %  {off:6x}  {m.group(2).strip()}")
    out = Path(args.annotate_out or f"/tmp/profile_kernel_{args.annotate}.txt")
    out.write_text(f"{args.annotate}: {sum(hits.values())} samples\n" + "\n".join(lines))
    print(f"{args.annotate}: {sum(hits.values())} samples by instruction in {out}; "
          "busiest 64-byte windows:")  # fmt: skip
    for w, share in windows.most_common(10):
        print(f"  {100 * share:5.1f} %  +{64 * w:x}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--sensor", default="ideal", choices=["ideal", "noise", "realistic"]
    )
    ap.add_argument("--size", default="96x144")
    ap.add_argument("--repeats", type=int, default=8)
    ap.add_argument("--out", default=None)
    ap.add_argument("--annotate", default=None, metavar="FUNC")
    ap.add_argument("--annotate-out", default=None)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    perf = shutil.which("perf")
    if perf is None:
        print("profile_kernel: `perf` not found (Debian: apt install linux-perf)")
        sys.exit(2)
    with tempfile.TemporaryDirectory() as tmp:
        data, res = Path(tmp) / "perf.data", Path(tmp) / "child.json"
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(tmp) / "numba"))
        cmd = [perf, "record", "-q", "-e", "cpu-clock", "-F", "2000", "-o", str(data),
               "--", sys.executable, __file__, "--sensor", args.sensor, "--size",
               args.size, "--repeats", str(args.repeats), "--child", str(res)]  # fmt: skip
        if args.annotate:
            cmd += ["--annotate", args.annotate]
        run = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if run.returncode != 0 or not res.exists():
            tail = (run.stderr.strip().splitlines() or ["no output"])[-1]
            print(f"profile_kernel: perf record failed: {tail}")
            sys.exit(2)
        rep = subprocess.run(
            [perf, "report", "-i", str(data), "--stdio", "--sort", "sym"],
            capture_output=True, text=True,
        ).stdout  # fmt: skip
        child_res = json.loads(res.read_text())
        if "error" in child_res:
            print(f"profile_kernel: no kernel function named {child_res['error']!r}")
            sys.exit(2)
        Path(f"/tmp/perf-{child_res['pid']}.map").unlink(missing_ok=True)
        if args.annotate:
            annotate(perf, data, res, args)
    shares = {}
    for line in rep.splitlines():
        m = re.match(r"\s*([\d.]+)%\s+\[\.\]\s+evhsi_kernel:(\S+)", line)
        if m:
            shares[m.group(2)] = shares.get(m.group(2), 0.0) + float(m.group(1))
    total = sum(shares.values())
    if total == 0:
        print("profile_kernel: no samples in the kernel (perf map not read?)")
        sys.exit(2)
    from _common import matmul_gflops

    gflops = matmul_gflops()
    rows = {k: v / total for k, v in sorted(shares.items(), key=lambda kv: -kv[1])}
    print(f"{args.sensor}, {args.size}, one thread: {child_res['us_per_px']:.1f} µs/px "
          f"over {args.repeats} calls; float32 matmul {gflops:.1f} GFLOP/s")  # fmt: skip
    for k, v in rows.items():
        if v >= 0.005:
            print(f"  {100 * v:5.1f} %  {k}")
    if args.out:
        Path(args.out).write_text(json.dumps({
            "sensor": args.sensor, "size": args.size, "repeats": args.repeats,
            "us_per_px": child_res["us_per_px"], "pixels": child_res["pixels"],
            "share_of_kernel_samples": rows, "matmul_gflops": gflops,
        }, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
