"""CUDA kernel of the GPU path: each pixel's Gram matrix, priors and box QP on the
chip (numba's CUDA target), from the weighted rows that :func:`._problem.pixel_system`
forms (`return_rows=True`).

The JAX path on a GPU forms Q = RᵀR as a batched matrix product and solves it with
XLA's batched Cholesky (cuSOLVER): Q goes through the GPU's memory three times and the
Cholesky runs at ~1 TFLOP/s on an H100 (experiments/PERFORMANCE_LOG.md, "One GPU"). Here one
thread block (one warp) holds one pixel's system in shared memory from the first row
to the answer:

1. **Q from the rows' spans.** The rows are read four at a time (each thread's
   values into registers, then into shared memory); each row's nonzero span
   [lo, hi) is found (a warp vote), and each thread adds the four rows to its rows
   i of Q from the first column of the rows that reach i (the rows outside their
   span are exact zeros, so the sums are those of the dense product, in another
   order). Q's envelope (first nonzero column of each row) is kept as in the CPU's
   fused kernel (:mod:`._fused_jit`).
2. **Priors** `spec_w · S` and the ridge, as :func:`._problem._system`.
3. **Envelope LDLᵀ and the primal active-set method** of
   :func:`._fused_jit._box_qp` (the same steps as
   :func:`._solvers.active_set_batch`): right-looking, the update of step k limited
   to the rows whose envelope reaches column k, one barrier per step; column k is
   kept contiguous in a small buffer, so the update's inner loop steps both of its
   operands by one.

Q is then kept in a global scratch array (`Q_GLOBAL`) and the factor takes its
place in shared memory: one triangle per block instead of two, 15 blocks per
multiprocessor instead of 9 (Q is read again only by the active-set steps and the
final gradient). The hot loops index in 32 bits (`_u`, `_tri`): numba's integers are
64-bit, and a profile of the first kernel (Nsight Compute, H100) found it
instruction-bound, much of its ~134k instructions per pixel 64-bit index
arithmetic (experiments/PERFORMANCE_LOG.md, "One GPU").

Arithmetic is float32, as the JAX path's (its accuracy against a float64 solve is
measured by `experiments/bench_gpu_kernel.py`). The warp votes and shuffles have
shared-memory stand-ins under numba's CUDA simulator, which runs the rest of the
kernel as it is on a CPU (`NUMBA_ENABLE_CUDASIM=1`; the tests do, on a few pixels).
"""

from __future__ import annotations

import contextlib
import functools
import os

import numpy as np

if not hasattr(np, "row_stack"):
    # numba-cuda (0.2x) registers an overload of np.row_stack when it first compiles;
    # NumPy 2.5 removed that alias of np.vstack (seen on the H100's image).
    np.row_stack = np.vstack

from numba import cuda, float32, int32  # noqa: E402

#: Threads per pixel (one warp).
THREADS = 32
#: Threads per pixel under the simulator (its barriers are slow; any number ≥ RB).
SIM_THREADS = 4
#: Q in a global scratch array after its assembly (one shared triangle per pixel:
#: ~15 kB of shared memory per block instead of ~25, so 15 resident blocks per
#: multiprocessor instead of 9; on the H100 0.152 s against 0.218 s for the
#: 1280×720 sweep, experiments/PERFORMANCE_LOG.md, "One GPU").
Q_GLOBAL = True
#: Cap on registers per thread (None: the compiler's choice).
MAX_REGISTERS = None
#: The next pass's rows read while the current one is added (see `make_kernel`;
#: on the H100 with Q in shared memory 0.198 s against 0.218 s, at 118 registers
#: instead of 79; not measured with the default, Q_GLOBAL; PERFORMANCE_LOG.md, "One GPU").
PREFETCH = False
#: Source lines in the compiled code, for a profiler (`EVHSI_CUDA_LINEINFO=1`).
LINEINFO = os.environ.get("EVHSI_CUDA_LINEINFO", "") not in ("", "0")
#: The compiled kernel kept on disk between processes (numba-cuda's cache, for the
#: default compile options; `EVHSI_CUDA_CACHE=0` turns it off).
CACHE = os.environ.get("EVHSI_CUDA_CACHE", "1") not in ("", "0")
#: Rows added to Q per pass (per barrier; the accumulation is written out for 4).
RB = 4


def _kernel_jit(jit, opts: dict, cache: bool):
    """`jit(**opts)` as a decorator, with numba's on-disk cache when `cache` (its
    folder: `__pycache__` beside this module, else `$NUMBA_CACHE_DIR` or numba's
    user-wide cache folder), so a new process loads the compiled kernel instead of
    compiling it again. The cache entry's key holds the function's bytecode, the
    closure's contents (m, nt, the device functions) and the GPU's compute
    capability, but not the compile options: hence the cache only for the default
    options. numba refuses `cache=True` (RuntimeError) where no folder is writable:
    then the kernel is compiled in each process, as without the cache."""

    def wrap(fn):
        if cache:
            try:
                return jit(cache=True, **opts)(fn)
            except RuntimeError:
                pass
        return jit(**opts)(fn)

    return wrap


def _u(i):
    """An index as unsigned 32-bit: numba then drops the negative-index wraparound,
    and LLVM narrows the arithmetic whose result is cast so to 32 bits (numba's
    integers are 64-bit: each addition two instructions, and more for the
    wraparound)."""
    return np.uint32(i)


def _tri(i):
    """i (i + 1) / 2, the start of row i of a packed lower triangle, in 32 bits."""
    return np.uint32((np.uint32(i) * np.uint32(i + 1)) >> np.uint32(1))


@functools.cache
def make_kernel(m: int, nt: int = THREADS, q_global: bool = False,
                max_registers: int | None = None, prefetch: bool = False,
                lineinfo: bool = False):  # fmt: skip
    """The kernel for M = `m` channels and `nt` threads per pixel (shared-memory sizes
    and loop strides are compile-time). On a GPU `nt` must be 32 (one warp: the
    reductions are warp shuffles); the simulator takes any `nt` ≥ RB. `q_global`:
    Q kept in a global scratch array after its assembly (see the kernel).
    `max_registers`: a cap on registers per thread (more blocks per multiprocessor
    where registers limit them; spills go to local memory). `prefetch`: the next
    pass's rows are read from global memory while the current pass is added (else
    each pass waits for its own reads). `lineinfo`: source lines in the code, for a
    profiler."""
    nl = m * (m + 1) // 2
    nq = 1 if q_global else nl
    m1 = m + 1  # shapes of shared arrays: constants of the closure, not expressions
    nspan = 2 * RB
    nv = -(-m1 // nt)  # row values per thread
    nrow = RB * m1
    m2 = 2 * m
    sim = simulated()
    u = cuda.jit(device=True, inline=True)(_u)
    tri = cuda.jit(device=True, inline=True)(_tri)

    # Reductions over the block's threads: warp shuffles on a GPU; through shared
    # memory in the simulator (it has no shuffles).
    if sim:

        @cuda.jit(device=True)
        def red(v, t, buf, op):  # op 0: min, 1: max, 2: sum
            buf[t] = v
            cuda.syncthreads()
            r = buf[0]
            for s in range(1, nt):
                if op == 0:
                    r = min(r, buf[s])
                elif op == 1:
                    r = max(r, buf[s])
                else:
                    r += buf[s]
            cuda.syncthreads()
            return r

    else:

        @cuda.jit(device=True)
        def red(v, t, buf, op):
            for off in (16, 8, 4, 2, 1):
                w = cuda.shfl_xor_sync(0xFFFFFFFF, v, off)
                if op == 0:
                    v = min(v, w)
                elif op == 1:
                    v = max(v, w)
                else:
                    v += w
            return v

    if sim:

        @cuda.jit(device=True)
        def span_of(rows, rr, t, ibuf):
            """[lo, hi): the nonzero channels of row `rr` of `rows` (lo = m, hi = 0
            when none), the same in every thread."""
            lo = m
            hi = 0
            for c in range(t, m, nt):
                if rows[rr * m1 + c] != 0.0:
                    lo = min(lo, c)
                    hi = c + 1
            return red(int32(lo), t, ibuf, 0), red(int32(hi), t, ibuf, 1)

    else:

        @cuda.jit(device=True)
        def span_of(rows, rr, t, ibuf):
            lo = m
            hi = 0
            for c0 in range(0, m, 32):  # one vote per 32 channels
                c = c0 + t
                nz = c < m and rows[rr * m1 + c] != 0.0
                mask = cuda.ballot_sync(0xFFFFFFFF, nz)
                if mask != 0:
                    lo = min(lo, c0 + cuda.ffs(mask) - 1)
                    hi = max(hi, c0 + 32 - cuda.clz(mask))
            return lo, hi

    @cuda.jit(device=True, inline=True)
    def fetch(buf, ev, ev_w, drift, b, r0, n_ev, n_rows, use_w, t):
        """buf[rr, kk] ← row r0 + rr at channel t + kk·nt: event rows times their
        weights, then the drift rows, zero past the last row."""
        for rr in range(RB):
            r = r0 + rr
            w = float32(1.0)
            if r < n_ev and use_w != 0:
                w = ev_w[b, r]
            for kk in range(nv):
                c = t + kk * nt
                v = float32(0.0)
                if c < m1:
                    if r < n_ev:
                        v = ev[b, r, c] * w
                    elif r < n_rows:
                        v = drift[b, r - n_ev, c]
                buf[rr, kk] = v

    @cuda.jit(device=True)
    def factor(qs, lf, col, invd, free, reach, iflag, t, init):
        """lf ← the LDLᵀ factor of Q restricted to the free variables (identity on
        the fixed ones), right-looking, in place over the envelope: column k of lf
        keeps the trailing matrix's column at step k (c), so that
        L[i, k] = c_i / c_k and D_k = c_k; invd[k] = 1 / c_k. One barrier per
        step: every thread reads the column k the last step finished and updates
        its own rows i > k. Column k is also kept contiguous in `col` (two
        buffers of M, by the parity of k), written by the step before from the
        rows it updated: the update's inner loop then steps both operands by
        one. iflag[0] = 1 when a pivot is not > 0. `init`: lf ← Q first (else lf
        already holds Q and every variable is free)."""
        for i in range(m if init else 0):
            fi = free[i]
            oi = tri(i)
            for j in range(t, i + 1, nt):
                v = float32(0.0)
                if fi != 0 and free[j] != 0:
                    v = qs[u(oi + j)]
                elif i == j:
                    v = float32(1.0)
                lf[u(oi + j)] = v
        cuda.syncthreads()
        i = u(1 + t)
        while i < reach[0]:  # column 0
            col[i] = lf[tri(i)]
            i = u(i + nt)
        cuda.syncthreads()
        bad = 0
        for k in range(m):
            dk = lf[u(tri(k) + k)]
            if not dk > 0.0:
                bad = 1
                break
            ik = float32(1.0) / dk
            if t == 0:
                invd[k] = ik
            rk = reach[k]
            cb = u((k & 1) * m)  # column k: col[cb + j]; column k + 1: col[nb + i]
            nb = u(m - (k & 1) * m)
            i = u(k + 1 + t)  # (the step's loops in 32 bits: while, not range)
            while i < rk:
                p = u(tri(i) + k + 1)  # lf[i, k + 1]
                cik = col[u(cb + i)]
                if cik != 0.0:
                    # lf[i, j] -= f lf[j, k] for k < j <= i; the updated
                    # lf[i, k + 1] is the next step's column.
                    f = cik * ik
                    q = u(cb + k + 1)
                    v = lf[p] - f * col[q]
                    lf[p] = v
                    col[u(nb + i)] = v
                    p = u(p + 1)
                    q = u(q + 1)
                    n = u(i - k - 1)
                    while n >= 4:  # four entries per iteration, loads first
                        a0 = lf[p]
                        a1 = lf[p + 1]
                        a2 = lf[p + 2]
                        a3 = lf[p + 3]
                        c0 = col[q]
                        c1 = col[q + 1]
                        c2 = col[q + 2]
                        c3 = col[q + 3]
                        lf[p] = a0 - f * c0
                        lf[p + 1] = a1 - f * c1
                        lf[p + 2] = a2 - f * c2
                        lf[p + 3] = a3 - f * c3
                        p = u(p + 4)
                        q = u(q + 4)
                        n = u(n - 4)
                    while n > 0:
                        lf[p] -= f * col[q]
                        p = u(p + 1)
                        q = u(q + 1)
                        n = u(n - 1)
                else:
                    col[u(nb + i)] = lf[p]
                i = u(i + nt)
            # Rows that column k + 1 reaches and column k did not: their entries.
            i = u(max(rk, k + 2) + t)
            r1 = reach[min(k + 1, m - 1)]
            while i < r1:
                col[u(nb + i)] = lf[u(tri(i) + k + 1)]
                i = u(i + nt)
            cuda.syncthreads()
        if t == 0:
            iflag[0] = bad
        cuda.syncthreads()

    @cuda.jit(device=True)
    def solve(lf, invd, free, first, reach, qv, out, t):
        """out = −Q_free⁻¹ q on the free variables (0 on the fixed ones) from the
        LDLᵀ factor: z = L⁻¹b, w = D⁻¹z, out = L⁻ᵀw, one barrier per step."""
        for i in range(t, m, nt):
            out[i] = -qv[i] if free[i] != 0 else float32(0.0)
        cuda.syncthreads()
        for k in range(m):
            zk = out[k] * invd[k]
            if zk != 0.0:
                i = u(k + 1 + t)
                rk = reach[k]
                while i < rk:
                    out[i] -= lf[u(tri(i) + k)] * zk
                    i = u(i + nt)
            cuda.syncthreads()
        for i in range(t, m, nt):
            out[i] *= invd[i]
        cuda.syncthreads()
        for k in range(m - 1, -1, -1):
            xk = out[k]
            if xk != 0.0:
                ok = tri(k)
                j = u(first[k] + t)
                while j < k:
                    out[j] -= lf[u(ok + j)] * invd[j] * xk
                    j = u(j + nt)
            cuda.syncthreads()
        for i in range(t, m, nt):
            if free[i] == 0:
                out[i] = float32(0.0)
        cuda.syncthreads()

    @cuda.jit(device=True)
    def gradient(qs, qv, first, reach, x, g, t):
        """g = Q x + q (Q symmetric, its lower triangle inside the envelope)."""
        for i in range(t, m, nt):
            s = qv[i]
            oi = tri(i)
            for j in range(first[i], i + 1):
                s += qs[u(oi + j)] * x[j]
            oj = tri(i + 1) + i  # (i + 1, i)
            for j in range(i + 1, reach[i]):
                s += qs[u(oj)] * x[j]
                oj += j + 1
            g[i] = s
        cuda.syncthreads()

    opts = {} if sim or max_registers is None else {"max_registers": max_registers}
    if lineinfo and not sim:
        opts["lineinfo"] = True
    # Kept on disk (see `_kernel_jit`) with the default compile options only.
    cache = CACHE and not sim and not opts

    @_kernel_jit(cuda.jit, opts, cache)
    def kernel(
        ev, use_w, ev_w, ev_n, drift, spec, spec_first, spec_w, ridge_rel, spec_trace,
        tol, max_iters, qg, out_x, out_kkt, out_steps,
    ):  # fmt: skip
        b = cuda.blockIdx.x
        t = cuda.threadIdx.x
        if b >= out_x.shape[0]:
            return
        if ev_n[b] <= 0:  # a padding slot (a pixel without events is never solved)
            for i in range(t, m, nt):
                out_x[b, i] = float32(0.0)
            if t == 0:
                out_kkt[b] = np.nan
                out_steps[b] = 0
            return
        qs = cuda.shared.array(nq, float32)
        lf = cuda.shared.array(nl, float32)
        # Q is accumulated in shared memory; with `q_global` in `lf` and kept in the
        # global scratch `qg[b]` from the factorisation on (one shared triangle per
        # pixel instead of two: 15 blocks per multiprocessor instead of 9).
        if q_global:
            acc = lf
            qsrc = qg[b]
        else:
            acc = qs
            qsrc = qs
        rows = cuda.shared.array(nrow, float32)  # (RB, M + 1), row-major
        qv = cuda.shared.array(m, float32)
        invd = cuda.shared.array(m, float32)
        col = cuda.shared.array(m2, float32)  # the factor's column k
        x = cuda.shared.array(m, float32)
        p = cuda.shared.array(m, float32)
        g = cuda.shared.array(m, float32)
        free = cuda.shared.array(m, int32)
        first = cuda.shared.array(m, int32)
        reach = cuda.shared.array(m, int32)
        span = cuda.shared.array(nspan, int32)
        iflag = cuda.shared.array(3, int32)  # factorisation failed, done, blocking j
        fsh = cuda.shared.array(1, float32)  # the blocked step's length
        ibuf = cuda.shared.array(nt, int32)  # the simulator's reductions
        fbuf = cuda.shared.array(nt, float32)
        for e in range(t, nl, nt):
            acc[u(e)] = float32(0.0)
        for i in range(t, m, nt):
            qv[i] = float32(0.0)
            first[i] = i
        # 1. Q += Σ r rᵀ, q += Σ r c over the rows, RB rows per pass: the pass's rows
        # (dense, zero outside their spans) go to shared memory with their spans,
        # then thread t adds them to the rows i ≡ t (mod nt) of Q (below).
        n_ev = ev_n[b]
        n_rows = n_ev + drift.shape[1]
        # Thread t's values of a pass's rows (channels t, t + nt, ...), in registers:
        # with `prefetch` the next pass's are read before this pass is added, so
        # that the global reads' latency hides behind the arithmetic.
        buf = cuda.local.array((RB, nv), float32)
        if prefetch:
            fetch(buf, ev, ev_w, drift, b, 0, n_ev, n_rows, use_w, t)
        for r0 in range(0, n_rows, RB):
            if not prefetch:
                fetch(buf, ev, ev_w, drift, b, r0, n_ev, n_rows, use_w, t)
            for rr in range(RB):
                for kk in range(nv):
                    c = t + kk * nt
                    if c < m1:
                        rows[rr * m1 + c] = buf[rr, kk]
            cuda.syncthreads()
            if prefetch:
                fetch(buf, ev, ev_w, drift, b, r0 + RB, n_ev, n_rows, use_w, t)
            for rr in range(RB):
                lo, hi = span_of(rows, rr, t, ibuf)
                if t == 0:
                    span[2 * rr] = lo
                    span[2 * rr + 1] = hi
            cuda.syncthreads()
            lo_all = m
            hi_all = 0
            for rr in range(RB):
                if span[2 * rr + 1] > span[2 * rr]:
                    lo_all = min(lo_all, span[2 * rr])
                    hi_all = max(hi_all, span[2 * rr + 1])
            # Thread t adds the pass's rows to the rows i ≡ t (mod nt) of Q, from the
            # first column of the pass's rows that reach i (their values at i in
            # registers, the rows' values at j the same for all threads: one
            # shared read each), one read-modify-write of Q per entry; 32-bit
            # indices (numba's default 64-bit arithmetic doubles the instructions).
            for i in range(lo_all + t, hi_all, nt):
                js = i + 1
                for rr in range(RB):
                    if span[2 * rr] <= i < span[2 * rr + 1]:
                        js = min(js, span[2 * rr])
                if js > i:
                    continue
                if js < first[i]:
                    first[i] = js
                ui = u(i)
                a0 = rows[ui]
                a1 = rows[ui + m1]
                a2 = rows[ui + 2 * m1]
                a3 = rows[ui + 3 * m1]
                qv[i] += (a0 * rows[m] + a1 * rows[m1 + m]) + (
                    a2 * rows[2 * m1 + m] + a3 * rows[3 * m1 + m]
                )
                o = u(tri(i) + js)
                q = u(js)
                n = u(i + 1 - js)
                while n >= 2:  # two entries per iteration, their loads first
                    b0 = rows[q]
                    b1 = rows[q + m1]
                    b2 = rows[q + 2 * m1]
                    b3 = rows[q + 3 * m1]
                    c0 = rows[q + 1]
                    c1 = rows[q + 1 + m1]
                    c2 = rows[q + 1 + 2 * m1]
                    c3 = rows[q + 1 + 3 * m1]
                    q0 = acc[o]
                    q1 = acc[o + 1]
                    acc[o] = q0 + ((a0 * b0 + a1 * b1) + (a2 * b2 + a3 * b3))
                    acc[o + 1] = q1 + ((a0 * c0 + a1 * c1) + (a2 * c2 + a3 * c3))
                    o = u(o + 2)
                    q = u(q + 2)
                    n = u(n - 2)
                if n > 0:
                    acc[o] += (a0 * rows[q] + a1 * rows[q + m1]) + (
                        a2 * rows[q + 2 * m1] + a3 * rows[q + 3 * m1]
                    )
            cuda.syncthreads()
        # 2. Priors: spec_w S inside its envelope, the ridge on the diagonal.
        sw = spec_w[b]
        tr = float32(0.0)
        for i in range(t, m, nt):
            tr += acc[u(tri(i) + i)]
        tr = red(tr, t, fbuf, 2)
        ridge = ridge_rel * ((tr + sw * spec_trace) / float32(m) + float32(1e-30))
        for i in range(t, m, nt):
            oi = tri(i)
            for j in range(spec_first[i], i + 1):
                acc[u(oi + j)] += sw * spec[i, j]
            acc[u(oi + i)] += ridge
            if spec_first[i] < first[i]:
                first[i] = spec_first[i]
            free[i] = 1
        cuda.syncthreads()
        # The rows each column of the factor reaches: rows i with first[i] <= k.
        for k in range(t, m, nt):
            reach[k] = k + 1
        cuda.syncthreads()
        for i in range(t, m, nt):
            cuda.atomic.max(reach, first[i], i + 1)
        cuda.syncthreads()
        if t == 0:
            for k in range(1, m):
                if reach[k] < reach[k - 1]:
                    reach[k] = reach[k - 1]
        qmax = float32(0.0)
        for i in range(t, m, nt):
            qmax = max(qmax, abs(acc[u(tri(i) + i)]))
        qmax = red(qmax, t, fbuf, 1)
        cuda.syncthreads()
        if q_global:
            for e in range(t, nl, nt):
                qsrc[u(e)] = acc[u(e)]
            cuda.syncthreads()
        # 3. The unconstrained minimiser, then the active-set steps (_box_qp).
        # (with `q_global`, lf still holds Q: the first factorisation starts there)
        factor(qsrc, lf, col, invd, free, reach, iflag, t, not q_global)
        steps = 0
        failed = iflag[0] != 0
        if not failed:
            solve(lf, invd, free, first, reach, qv, x, t)
            if t == 0:
                neg = 0
                for i in range(m):
                    if x[i] < 0.0:
                        neg = 1
                    if x[i] <= 0.0:
                        x[i] = float32(0.0)
                        free[i] = 0
                iflag[1] = 1 - neg  # done
            cuda.syncthreads()
        while not failed and iflag[1] == 0 and steps < max_iters:
            steps += 1
            factor(qsrc, lf, col, invd, free, reach, iflag, t, True)
            if iflag[0] != 0:
                failed = True
                break
            solve(lf, invd, free, first, reach, qv, p, t)
            if t == 0:
                jb = -1
                best = float32(np.inf)
                for i in range(m):
                    if free[i] != 0 and p[i] < 0.0:
                        ratio = x[i] / (x[i] - p[i])
                        if ratio < best:
                            best = ratio
                            jb = i
                iflag[2] = jb
                fsh[0] = min(max(best, float32(0.0)), float32(1.0))
            cuda.syncthreads()
            jb = iflag[2]
            if jb >= 0:  # blocked: move to the first bound, fix it
                alpha = fsh[0]
                for i in range(t, m, nt):
                    x[i] = max(x[i] + alpha * (p[i] - x[i]), float32(0.0))
                cuda.syncthreads()
                if t == 0:
                    x[jb] = float32(0.0)
                    free[jb] = 0
                cuda.syncthreads()
                continue
            gradient(qsrc, qv, first, reach, p, g, t)
            if t == 0:
                pmax = float32(1e-30)
                for i in range(m):
                    pmax = max(pmax, abs(p[i]))
                lim = -tol * qmax * pmax
                jr = -1
                best = float32(np.inf)
                for i in range(m):
                    if free[i] == 0 and g[i] < lim and g[i] < best:
                        best = g[i]
                        jr = i
                for i in range(m):
                    x[i] = p[i]
                if jr >= 0:
                    free[jr] = 1
                else:
                    iflag[1] = 1
            cuda.syncthreads()
        # 4. The answer and its KKT residual (NaN and -1 when a factorisation failed).
        if failed:
            for i in range(t, m, nt):
                out_x[b, i] = np.nan
            if t == 0:
                out_kkt[b] = np.nan
                out_steps[b] = -1
            return
        gradient(qsrc, qv, first, reach, x, g, t)
        kkt = float32(0.0)
        for i in range(t, m, nt):
            kkt = max(kkt, abs(x[i] - max(x[i] - g[i] / qmax, float32(0.0))))
            out_x[b, i] = x[i]
        kkt = red(kkt, t, fbuf, 1)
        if t == 0:
            out_kkt[b] = kkt
            out_steps[b] = steps

    return kernel


def prior_envelope(spec: np.ndarray) -> np.ndarray:
    """First nonzero column of each row of the prior S (its diagonal if none)."""
    m = spec.shape[0]
    nz = np.abs(np.tril(spec)) > 0
    nz[np.arange(m), np.arange(m)] = True
    return np.argmax(nz, axis=1).astype(np.int32)


_PRIORS: dict = {}


def _prior_on_device(spec):
    """The prior matrix (float32), its envelope and trace, on the device once per
    prior."""
    spec = np.asarray(spec, np.float32)
    key = (spec.shape, spec.tobytes())
    if key not in _PRIORS:
        first = prior_envelope(spec)
        tr = np.float32(np.trace(spec.astype(np.float64)))
        if simulated():
            _PRIORS[key] = (spec, first, tr)
        else:
            _PRIORS[key] = (cuda.to_device(spec), cuda.to_device(first), tr)
    return _PRIORS[key]


def launch(ev, ev_w, ev_n, drift, spec_w, spec, ridge_rel, tol, max_iters, out_x,
           out_kkt, out_steps, stream=0, threads=THREADS, q_global=Q_GLOBAL,
           max_registers=MAX_REGISTERS, prefetch=PREFETCH):  # fmt: skip
    """Solve the pixels of one batch: `ev` (B, K, M+1) event rows with weights `ev_w`
    (B, K; None: 1), of which the first `ev_n` (B,) are used (the rest is padding;
    a pixel with none is a padding slot: its answer is 0, KKT NaN, not solved),
    `drift` (B, G, M+1) anti-drift (and dark-prior) rows, prior weight `spec_w` (B,),
    the prior matrix `spec` (M, M). Outputs (B, M), (B,), (B,) are written in place.
    Arrays: anything numba's CUDA target takes (device arrays, or host arrays under
    the simulator). `threads` per pixel: any number ≥ RB (the simulator's barriers
    are slow: the tests use a few)."""
    d_spec, d_first, tr = _prior_on_device(spec)
    m = d_spec.shape[0]
    kern = make_kernel(m, threads, q_global, max_registers, prefetch, LINEINFO)
    b = out_x.shape[0]
    if q_global:
        nl = m * (m + 1) // 2
        qg = np.zeros((b, nl), np.float32) if simulated() else _scratch(b, nl)
    else:
        qg = np.zeros((1, 1), np.float32) if simulated() else _dummy()
    use_w = ev_w is not None
    if not use_w:
        ev_w = np.ones((1, 1), np.float32) if simulated() else _dummy()
    kern[b, threads, stream](
        ev, np.int32(use_w), ev_w, ev_n, drift, d_spec, d_first, spec_w,
        np.float32(ridge_rel), tr, np.float32(tol), np.int32(max_iters), qg, out_x,
        out_kkt, out_steps,
    )  # fmt: skip


_SCRATCH: dict = {}


def _scratch(b, nl):
    """The global Q scratch of `q_global`, kept between launches (grown as needed)."""
    have = _SCRATCH.get("q")
    if have is None or have.shape[0] < b or have.shape[1] != nl:
        _SCRATCH["q"] = have = cuda.device_array((b, nl), np.float32)
    return have


@functools.cache
def _dummy():
    return cuda.to_device(np.ones((1, 1), np.float32))


def variant(spec: str) -> dict:
    """The keyword arguments of :func:`solve_rows` for a kernel variant written
    `PLACE:REGS[:pf|nopf]` (the benchmarks' `--variants`): Q in `shared` memory or
    a `global` scratch, a register cap or `none`, the next pass's rows read ahead
    (`pf`) or not (`nopf`; default `PREFETCH`)."""
    parts = spec.split(":")
    place, regs, flags = parts[0], parts[1] if len(parts) > 1 else "", parts[2:]
    if (
        place not in ("shared", "global") or not (regs == "none" or regs.isdigit())
        or flags not in ([], ["pf"], ["nopf"])
    ):  # fmt: skip
        raise ValueError(f"kernel variant {spec!r}: PLACE:REGS[:pf|nopf]")
    return {
        "q_global": place == "global",
        "max_registers": int(regs) if regs != "none" else None,
        "prefetch": "pf" in flags or (PREFETCH and "nopf" not in flags),
    }


def simulated() -> bool:
    """True when numba's CUDA target is its CPU simulator (`NUMBA_ENABLE_CUDASIM=1`)."""
    from numba import config

    return bool(config.ENABLE_CUDASIM)


def as_cuda(a):
    """A JAX (or CuPy) device array as a numba device array, without a copy (the CUDA
    array interface, else DLPack through CuPy); under the simulator a host array."""
    if simulated():
        return np.array(a)  # a writable copy (the simulator copies arguments back)
    try:
        return cuda.as_cuda_array(a)
    except Exception:  # no __cuda_array_interface__: go through DLPack
        import cupy

        return cuda.as_cuda_array(cupy.from_dlpack(a))


def solve_rows(rows, ev_n, spec, ridge_rel, tol, max_iters, ev_w=None,
               q_global=None, max_registers=None, prefetch=None, wait=True):  # fmt: skip
    """Box-QP answers of a batch of pixels from their rows (:class:`._problem.
    PixelRows` with a leading batch axis, float32, on the GPU): `(x, kkt, steps)` as
    numba device arrays (host arrays under the simulator). The JAX arrays must be
    ready (`jax.block_until_ready`); the kernel runs on numba's default stream and
    this returns after it finished, or (`wait=False`) right after the launch: then
    the caller keeps the inputs referenced and calls `cuda.synchronize()`
    (:func:`synchronize`) before anything reads the answers or frees the inputs.
    `ev_n` (B,) int32: each pixel's event rows (the rest of `rows.events` is
    padding); `ev_w`: optional weights of the event rows."""
    ev = rows.events
    b = ev.shape[0]
    m = ev.shape[2] - 1
    if ev_w is not None:
        ev_w = as_cuda(ev_w)
    if simulated():
        out_x = np.zeros((b, m), np.float32)
        out_kkt = np.zeros(b, np.float32)
        out_steps = np.zeros(b, np.int32)
    else:
        out_x = cuda.device_array((b, m), np.float32)
        out_kkt = cuda.device_array(b, np.float32)
        out_steps = cuda.device_array(b, np.int32)
    launch(
        as_cuda(ev), ev_w, as_cuda(ev_n), as_cuda(rows.drift),
        as_cuda(rows.spec_weight), spec, ridge_rel, tol, max_iters, out_x, out_kkt,
        out_steps, threads=SIM_THREADS if simulated() else THREADS,
        q_global=Q_GLOBAL if q_global is None else q_global,
        max_registers=MAX_REGISTERS if max_registers is None else max_registers,
        prefetch=PREFETCH if prefetch is None else prefetch,
    )  # fmt: skip
    if wait:
        synchronize()
    return out_x, out_kkt, out_steps


def deferred_frees():
    """A context in which numba frees no device memory (`cuda.defer_cleanup`: a free
    would wait for the whole device, JAX's work included); a no-op under the
    simulator."""
    return contextlib.nullcontext() if simulated() else cuda.defer_cleanup()


def synchronize():
    """Wait for every kernel launched (numba's CUDA target; nothing under the
    simulator, whose launches run to their end)."""
    if not simulated():
        cuda.synchronize()


def to_jax(a):
    """A numba device array as a JAX array on the same GPU (DLPack, through CuPy
    where numba's array has no `__dlpack__`; a host round trip as the last resort);
    under the simulator, from the host array."""
    import jax
    import jax.numpy as jnp

    if simulated():
        return jnp.asarray(a)
    try:
        return jax.dlpack.from_dlpack(a)
    except Exception:
        pass
    try:
        import cupy

        return jax.dlpack.from_dlpack(cupy.asarray(a))
    except Exception:
        return jax.device_put(a.copy_to_host())


@functools.cache
def self_check(m: int) -> str | None:
    """Whether the kernel compiles and solves on this GPU (None) or why not (the
    error, one line): what `backend="auto"` asks before it picks the kernel, once
    per process and channel count, so that a numba whose CUDA target cannot build or
    launch (driver, toolkit) leaves `auto` on JAX instead of failing. Two pixels of
    `m` channels, each with one row per channel asking x = 0.5, must come back
    within 0.02 of 0.5 (the priors' weights here are tiny)."""
    from types import SimpleNamespace

    from ._problem import spectral_prior_matrix

    try:
        b = 2
        ev = np.zeros((b, m, m + 1), np.float32)
        ev[:, np.arange(m), np.arange(m)] = 1.0
        ev[:, :, m] = -0.5
        arrays = (ev, np.zeros((b, 1, m + 1), np.float32), np.full(b, 1e-6, np.float32),
                  np.full(b, m, np.int32))  # fmt: skip
        if not simulated():
            # JAX arrays, as the reconstruction passes: the launch then has the same
            # argument types, so it loads (or compiles) the same kernel entry.
            import jax

            arrays = jax.block_until_ready(tuple(jax.device_put(a) for a in arrays))
        rows = SimpleNamespace(events=arrays[0], drift=arrays[1], spec_weight=arrays[2])
        x, _, steps = solve_rows(
            rows, arrays[3], spectral_prior_matrix(m, 0.3, "d2"), 1e-9, 1e-6, 48
        )  # fmt: skip
        if not simulated():
            x, steps = x.copy_to_host(), steps.copy_to_host()
    except Exception as err:  # (numba's errors are of many kinds)
        return f"{type(err).__name__}: {err}".splitlines()[0][:200]
    if not (np.all(steps >= 0) and np.all(np.abs(x - 0.5) < 0.02)):
        return f"wrong answers on the check problem (x in [{x.min()}, {x.max()}])"
    return None


def why_not(spec, cfg, dtype, mesh) -> str | None:
    """Why the CUDA kernel cannot solve this reconstruction (None: it can)."""
    import jax

    if spec.name != "active-set":
        return f"solver {spec.name!r} (the kernel is the active-set solver)"
    if not cfg.nonneg:
        return "nonneg=False (the kernel solves the box QP)"
    if np.dtype(dtype) != np.float32:
        return "a float64 rig (the kernel is float32)"
    if not simulated() and (jax.default_backend() != "gpu" or not cuda.is_available()):
        return "no CUDA GPU (JAX's default backend and numba's CUDA target)"
    if mesh is not None:
        return "a device mesh (it runs on one GPU: --devices 1)"
    return None


def resources(m: int, q_global: bool | None = None, max_registers: int | None = None,
              prefetch: bool | None = None):  # fmt: skip
    """Registers and local memory per thread, shared memory per block of the compiled
    kernel (after a launch compiled it; empty under the simulator); None: the
    module's defaults (`Q_GLOBAL`, `MAX_REGISTERS`, `PREFETCH`), as `solve_rows`."""
    kern = make_kernel(
        m, THREADS, Q_GLOBAL if q_global is None else q_global,
        MAX_REGISTERS if max_registers is None else max_registers,
        PREFETCH if prefetch is None else prefetch, LINEINFO,
    )  # fmt: skip
    out = {}
    for key in ("regs_per_thread", "local_mem_per_thread", "shared_mem_per_block"):
        try:
            v = getattr(kern, "get_" + key)()
            if isinstance(v, dict):  # per compiled signature (not specialised)
                v = max(v.values())
            out[key] = int(v)
        except Exception:  # the simulator, or an API without it
            pass
    return out
