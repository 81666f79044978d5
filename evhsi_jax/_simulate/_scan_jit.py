"""numba kernel of the simulator's pixel state machine on a CPU (imported on first use).

The same steps as :func:`evhsi_jax._model._sensor.exact_events_scan`, in float32 and in
the same order of operations with multiply-adds contracted as XLA does (so the same
crossings; a time may differ in its last bit where the two compilers round a
product differently: a timestamp then rarely falls on the other side of a µs), but the time
loop runs in compiled code instead of one XLA while-loop iteration per time sample,
and only the crossings come out — in `np.nonzero(fired)` order, step by step and
pixel by pixel within a step — instead of three dense `(t, pixels)` arrays that the
host then searched. Marked `no_type_check` so that the jaxtyping import hook of the
test suite leaves it to numba.
"""

from __future__ import annotations

from typing import no_type_check

import numpy as np

from .._base import njit


@njit(inline=True, fastmath={"contract"})
@no_type_check
def _safe_frac(num, den):
    if not abs(den) > np.float32(1e-12):
        return np.float32(0.0)
    f = num / den
    return min(max(f, np.float32(0.0)), np.float32(1.0))


@njit(fastmath={"contract"})
@no_type_check
def events_scan(
    log_i, t_us, thr_on, thr_off, refractory, r, t_free, pending, release,
    ref_noise, has_noise, capacity,
):  # fmt: skip
    """Run the state machine over `log_i` `(t, p)` at times `t_us` `(t,)`; the state
    `(r, t_free, pending)` `(p,)` is updated in place. `ref_noise` `(t-1, p)` is read
    only when `has_noise`. Returns `(step, pixel, time, is_on, n)` with room for
    `capacity` crossings; `n > capacity` means the arrays were too small (the caller
    retries with room for `n`; the state is then already advanced, so it must pass a
    copy)."""
    nt, p = log_i.shape
    step_o = np.empty(capacity, np.int32)
    pix_o = np.empty(capacity, np.int32)
    t_o = np.empty(capacity, np.float32)
    up_o = np.empty(capacity, np.bool_)
    n = 0
    zero = np.float32(0.0)
    for j in range(nt - 1):
        ta = t_us[j]
        tb = t_us[j + 1]
        dtab = tb - ta
        la_row = log_i[j]
        lb_row = log_i[j + 1]
        for q in range(p):
            la = la_row[q]
            lb = lb_row[q]
            eps = ref_noise[j, q] if has_noise else zero
            rq = r[q]
            pend = pending[q]
            tf = t_free[q]
            rel = pend and tf <= tb
            s = ta
            ls = la
            if rel:
                f_rel = _safe_frac(tf - ta, dtab)
                l_rel = la + f_rel * (lb - la)
                if release:
                    rq = l_rel + eps
                pend = False
                s = ta + f_rel * dtab
                ls = l_rel
            if pend:
                r[q] = rq
                continue
            c_on = thr_on[q]
            c_off = thr_off[q]
            beyond_on = ls >= rq + c_on
            beyond_off = ls <= rq - c_off
            up = (not beyond_off) and (lb >= rq + c_on or beyond_on)
            dn = (not up) and (lb <= rq - c_off or beyond_off)
            if up or dn:
                target = rq + c_on if up else rq - c_off
                if beyond_on or beyond_off:
                    tc = s
                else:
                    tc = s + _safe_frac(target - ls, lb - ls) * (tb - s)
                tf = tc + refractory
                pend = True
                if not release:
                    rq = target + eps
                if n < capacity:
                    step_o[n] = j
                    pix_o[n] = q
                    t_o[n] = tc
                    up_o[n] = up
                n += 1
            r[q] = rq
            t_free[q] = tf
            pending[q] = pend
    return step_o, pix_o, t_o, up_o, n
