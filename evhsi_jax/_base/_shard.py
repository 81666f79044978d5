"""Scale-out: the pixel axis across devices (`jax.sharding`) and hosts (`jax.distributed`).

Both heavy loops are embarrassingly parallel over pixels: the reconstruction solves one
QP per pixel, the simulator scans each column chunk independently. This module is the
plumbing only (mesh, host↔global arrays, processes); the sharded kernels live with the
stage that owns them (`_simulate.scan_chunks_sharded`,
`_reconstruct._pipeline.solve_chunk_sharded`), so imports flow one way. A one-axis
:class:`jax.sharding.Mesh` named `"pixels"` spans the devices; each compiled chunk is
cut into equal per-device blocks with :func:`jax.shard_map`, and every device runs the
*same* per-pixel kernel on its block as the single-device code does on a whole chunk —
no communication, and results equal the unsharded run (each pixel's arithmetic does not
depend on which pixels share its batch).

The same code runs on one CPU, on many CPU devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=N`, set before jax is imported), on
GPUs, and across hosts.

**Multi-host.** Every process runs the same program on the same inputs (each reads the
event file from shared storage and does the cheap host-side grouping itself); the mesh
spans all processes' devices, each process feeds only its own devices' blocks
(`jax.make_array_from_callback`), results are gathered back to every process
(`multihost_utils.process_allgather`), and only process 0 writes files. Start it with
:func:`initialize_distributed` (or `evhsi --distributed ...`) in every process, e.g.
two hosts::

    # host A                                   # host B
    EVHSI_COORDINATOR=hostA:1234 \\             EVHSI_COORDINATOR=hostA:1234 \\
    EVHSI_NUM_PROCESSES=2 EVHSI_PROCESS_ID=0 \\  EVHSI_NUM_PROCESSES=2 EVHSI_PROCESS_ID=1 \\
    evhsi --distributed reconstruct ...         evhsi --distributed reconstruct ...

On SLURM / Open MPI / TPU pods `jax.distributed.initialize()` finds these by itself, so
`--distributed` with no variables set is enough there.
"""

from __future__ import annotations

import concurrent.futures
import os
import socket
import sys
import threading
import time

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ._storage import one_line

__all__ = [
    "PIXELS",
    "pixel_mesh",
    "initialize_distributed",
    "is_main_process",
    "to_global",
    "to_host",
    "to_host_copy",
    "replicated",
    "mesh_size",
    "device_platform",
    "sub_batch_for",
    "chunk_groups",
    "usable_cores",
    "in_slices",
]

PIXELS = "pixels"
_ENV = {
    "coordinator_address": "EVHSI_COORDINATOR",
    "num_processes": "EVHSI_NUM_PROCESSES",
    "process_id": "EVHSI_PROCESS_ID",
}


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    timeout_s: int | None = None,
) -> bool:
    """Join a multi-host run (`jax.distributed.initialize`), once per process.

    Arguments left `None` are read from `EVHSI_COORDINATOR` (`host:port` of process
    0), `EVHSI_NUM_PROCESSES` and `EVHSI_PROCESS_ID`; if those are unset too, JAX's own
    cluster detection (SLURM, Open MPI, TPU) fills them in. Must run before any other
    JAX call. Returns True once initialised (also if it already was).

    `timeout_s` (default `EVHSI_DISTRIBUTED_TIMEOUT`, else 60 s) bounds the wait for
    the coordinator and the other processes (JAX's own default waits 300 s without a
    word, then aborts the process). A process other than 0 first checks that the
    coordinator's port answers, and raises `ConnectionError` if it does not within the
    time. Past the time, JAX's wait for the other processes cannot be interrupted: a
    watchdog then prints one line naming the coordinator to stderr and ends the
    process with exit status 2 (what JAX would do, with exit 134 and a stack dump).
    """
    if jax.distributed.is_initialized():
        return True
    if timeout_s is None:
        raw = os.environ.get("EVHSI_DISTRIBUTED_TIMEOUT", "60")
        try:
            timeout_s = int(raw)
        except ValueError:
            raise ValueError(
                f"EVHSI_DISTRIBUTED_TIMEOUT must be an integer, got {raw!r}"
            ) from None
    if timeout_s < 1:
        raise ValueError(f"the distributed timeout must be >= 1 s, got {timeout_s}")
    kw = {"coordinator_address": coordinator_address}
    kw["num_processes"], kw["process_id"] = num_processes, process_id
    for name, var in _ENV.items():
        if kw[name] is None and os.environ.get(var):
            raw = os.environ[var]
            try:
                kw[name] = raw if name == "coordinator_address" else int(raw)
            except ValueError:
                raise ValueError(f"{var} must be an integer, got {raw!r}") from None
    where = kw["coordinator_address"] or "the detected cluster"
    hint = "are all processes started and the coordinator reachable?"
    if kw["coordinator_address"] and kw["process_id"] not in (None, 0):
        _wait_for_port(kw["coordinator_address"], timeout_s, hint)
    deadline = time.monotonic() + timeout_s

    def give_up():
        sys.stderr.write(
            f"evhsi: error: could not join the multi-host run at {where} within "
            f"{timeout_s} s (EVHSI_DISTRIBUTED_TIMEOUT); {hint}\n"
        )
        sys.stderr.flush()
        os._exit(2)

    watchdog = threading.Timer(max(0.0, deadline - time.monotonic()), give_up)
    watchdog.daemon = True
    watchdog.start()
    try:
        jax.distributed.initialize(
            **{k: v for k, v in kw.items() if v is not None},
            initialization_timeout=int(timeout_s) + 30,  # the watchdog fires first
        )
    except (RuntimeError, ValueError) as err:  # XlaRuntimeError is a RuntimeError
        msg = one_line(err, 160)
        raise ConnectionError(
            f"could not join the multi-host run at {where} ({msg}); {hint}"
        ) from None
    finally:
        watchdog.cancel()
    return True


def _wait_for_port(address: str, timeout_s: float, hint: str) -> None:
    """Return once `host:port` accepts a TCP connection; `ConnectionError` after
    `timeout_s` seconds of trying."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"coordinator address must be host:port, got {address!r}")
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=2.0):
                return
        except OSError as err:
            if time.monotonic() >= deadline:
                raise ConnectionError(
                    f"the coordinator {address} did not answer within {timeout_s} s "
                    f"({err.strerror or err}); {hint}"
                ) from None
            time.sleep(0.2)


def is_main_process() -> bool:
    """True in process 0 (the one that writes files), and in any single-process run."""
    return jax.process_index() == 0


def pixel_mesh(devices=None) -> Mesh:
    """A one-axis mesh `("pixels",)` over `devices` (default: all, every host's).

    **Arguments:**

    - `devices`: a sequence of devices, or an int `n` for the first `n` of
      `jax.devices()`.
    """
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, int):
        if not 1 <= devices <= len(jax.devices()):
            raise ValueError(
                f"asked for {devices} devices, have {len(jax.devices())} "
                "(CPU: set XLA_FLAGS=--xla_force_host_platform_device_count=N "
                "before jax is imported)"
            )
        devices = jax.devices()[:devices]
    return Mesh(np.asarray(list(devices)), (PIXELS,))


def mesh_size(mesh: Mesh | None) -> int:
    """Devices in `mesh` (1 without one)."""
    return 1 if mesh is None else int(mesh.devices.size)


def to_global(mesh: Mesh, array, *, sharded: bool = True) -> jax.Array:
    """A host array (the same on every process) as a global array on `mesh`, its
    leading axis split over `"pixels"` (or replicated with `sharded=False`)."""
    array = np.asarray(array)
    sharding = NamedSharding(mesh, P(PIXELS) if sharded else P())
    if jax.process_count() == 1:
        return jax.device_put(array, sharding)
    return jax.make_array_from_callback(array.shape, sharding, lambda idx: array[idx])


def to_host(x) -> np.ndarray:
    """A (possibly multi-host) global array as one NumPy array on every process."""
    if jax.process_count() == 1 or x.is_fully_addressable:
        return np.asarray(x)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def to_host_copy(a: jax.Array, via_pinned: bool | None = None) -> np.ndarray:
    """A single-device array as a new writable NumPy array. From an accelerator
    (`via_pinned` None: not a CPU) through the host's pinned memory — the copy then
    runs at the bus's rate (a 1280×720 cube, 270 MB, in 6 ms on an H100, against
    0.2 s for JAX's own copy into pageable memory and 0.1 s more for NumPy's
    writable copy of it: `experiments/bench_gpu_transfer.py`) — and from there into
    the result on the usable cores (:func:`in_slices`: the fresh pages are touched
    by several at once). Below `PINNED_MIN_BYTES`, or where the device has no pinned
    host memory: `np.array`."""
    if via_pinned is None:
        via_pinned = next(iter(a.devices())).platform != "cpu"
    if not via_pinned or a.nbytes < PINNED_MIN_BYTES:
        return np.array(a)
    try:
        src = np.asarray(
            jax.device_put(a, a.sharding.with_memory_kind("pinned_host"))
        )  # fmt: skip
    except Exception:  # (a device or JAX without that memory kind)
        return np.array(a)
    out = np.empty_like(src)
    flat_in, flat_out = src.reshape(-1), out.reshape(-1)
    in_slices(flat_in.size, lambda i0, i1: np.copyto(flat_out[i0:i1], flat_in[i0:i1]))
    return out


#: Below this size :func:`to_host_copy` copies by `np.array`.
PINNED_MIN_BYTES = 1 << 24


def replicated(mesh, tree):
    """Array leaves of a parameter pytree (rig, tables) replicated on every device."""
    if jax.process_count() == 1:
        return tree
    return jax.tree.map(
        lambda a: to_global(mesh, a, sharded=False) if eqx.is_array(a) else a, tree
    )


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def in_slices(n: int, part, *, threaded: bool = True) -> None:
    """`part(i0, i1)` over slices covering `[0, n)`, four per worker on up to 8
    usable cores (for work that releases the GIL: NumPy's copies, numba's `nogil`
    kernels); once as `part(0, n)` when not `threaded`, on one core, or for n = 0."""
    workers = min(usable_cores(), 8)
    if not threaded or workers == 1 or n == 0:
        part(0, n)
        return
    step = -(-n // (4 * workers))
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda i: part(i, min(i + step, n)), range(0, n, step)))


def device_platform(mesh: Mesh | None = None) -> str:
    """The platform (`"cpu"`, `"gpu"`, …) of the devices a computation runs on: the
    mesh's, else JAX's default backend (batch sizes are chosen by it)."""
    if mesh is None:
        return jax.default_backend()
    return next(iter(mesh.devices.flat)).platform


def sub_batch_for(mesh: Mesh, sub: int) -> int:
    """The sub-batch a sharded solve can use on `mesh`: 1 on several CPU devices.

    XLA:CPU runs every CPU device's program on one shared thread pool, and its
    batched Cholesky (LAPACK FFI) splits the batch over that pool and blocks until
    the pieces are done; when every pool thread is a device program blocked that way,
    nothing runs the pieces (seen with 4 forced host devices on 2 cores: a hang, all
    threads in `ParallelBatchMap`). Single-matrix Cholesky calls do not split, so on
    several CPU devices each `lax.map` step solves one pixel. GPUs keep `sub`.
    """
    devices = list(mesh.devices.flat)
    if len(devices) > 1 and all(d.platform == "cpu" for d in devices):
        return 1
    return int(sub)


def chunk_groups(n_chunks: int, mesh: Mesh | None) -> list[list[int]]:
    """Chunk indices in groups of `mesh.size` (the last padded by repeating its final
    index; the caller discards repeats)."""
    d = mesh_size(mesh)
    groups = []
    for g0 in range(0, n_chunks, d):
        g = list(range(g0, min(g0 + d, n_chunks)))
        groups.append(g + [g[-1]] * (d - len(g)))
    return groups
