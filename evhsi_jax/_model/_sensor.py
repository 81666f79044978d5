"""Event triggering: the exact pixel state machine and its soft, differentiable relaxation.

Pixel model (paper Eq. 2). A pixel holds a reference log-level $r$. It fires an ON event
when $\\log(I+ε) \\ge r + C_{on}$ and an OFF event when $\\log(I+ε) \\le r - C_{off}$, then
is blind for the refractory time η; when η ends, its reference is reset to the log-level
*at that moment*, $r = \\log(I(τ_k + η) + ε)$ — the behaviour of the DVS reset switch,
and what makes each pair of events an exact constraint
$\\log(I(τ_k)+ε) - \\log(I(τ_{k-1}+η)+ε) = σ_k C$.

Between samples of the time grid the log-intensity is linear, so crossing times are
interpolated to sub-sample precision. The grid step never exceeds η, so at most one event
falls in a step; that is what lets a scan emit a fixed-shape output.

:func:`soft_event_counts` relaxes every decision of the same scan with a sigmoid of
temperature τ (log units): it returns expected ON/OFF counts per time step, and as
τ → 0 it reproduces the exact scan step for step. Its gradients are finite everywhere
(divisions are guarded, logs see $I + ε > 0$).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "exact_events_scan",
    "soft_event_counts",
    "initial_state",
    "photoreceptor_lowpass",
]

_FAR_PAST = -1e9  # µs: "released long ago"


def initial_state(log_i0: Float[Array, " p"]):
    """Pixel state at the first sample: reference = current level, sensitive."""
    return (
        log_i0,
        jnp.full_like(log_i0, _FAR_PAST),
        jnp.zeros(log_i0.shape, bool),
    )


def _safe_frac(num, den):
    ok = jnp.abs(den) > 1e-12
    return jnp.clip(jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0), 0.0, 1.0)


def exact_events_scan(
    log_i: Float[Array, "t p"],
    t_us: Float[Array, " t"],
    threshold_on: Float[Array, " p"],
    threshold_off: Float[Array, " p"],
    refractory_us: Float[Array, ""],
    state=None,
    *,
    reset_mode: str = "release",
    reference_noise: Float[Array, "t1 p"] | None = None,
):
    """Run the exact pixel state machine over a time grid.

    **Arguments:**

    - `log_i`: $\\log(I+ε)$ at the grid times, shape `(t, p)`.
    - `t_us`: grid times in µs, shape `(t,)`, increasing, steps ≤ `refractory_us`.
    - `threshold_on`, `threshold_off`: per-pixel thresholds, log units, shape `(p,)`.
    - `refractory_us`: η in µs.
    - `state`: `(reference, release_time_us, pending)` from a previous call (times in
      this call's frame), or `None` to start at the first sample.
    - `reset_mode`: `"release"` (paper Eq. 2: the reference becomes the level at the end
      of the refractory period) or `"event"` (the reference steps by ±C at each event; a
      crossing during the refractory period fires when it ends).
    - `reference_noise`: optional per-step offsets (log units), shape `(t-1, p)`, added
      to the reference whenever it is set in that step (at release, or at the event in
      `"event"` mode): per-crossing threshold noise — each crossing then needs
      $C + ε$ with a fresh $ε$ (the reset/kTC noise of a real pixel acts the same way).
      `None`: the ideal pixel (the same program as before this option existed).

    **Returns:** `(fired, time_us, is_on)`, each of shape `(t-1, p)` — whether the pixel
    fired in step `j` (between samples `j` and `j+1`), the interpolated event time, and
    its polarity — and the final state.
    """
    if state is None:
        state = initial_state(log_i[0])

    def step(carry, inp):
        r, t_free, pending = carry
        la, lb, ta, tb = inp[:4]
        eps = inp[4] if reference_noise is not None else 0.0
        # End of refractory inside this step: reset the reference to the level then.
        rel = pending & (t_free <= tb)
        f_rel = _safe_frac(t_free - ta, tb - ta)
        l_rel = la + f_rel * (lb - la)
        if reset_mode == "release":
            r = jnp.where(rel, l_rel + eps, r)
        pending = pending & ~rel
        s = jnp.where(rel, ta + f_rel * (tb - ta), ta)
        ls = jnp.where(rel, l_rel, la)
        # Already past a threshold when sensitivity starts ("event" mode: a crossing
        # during the refractory period): fire right at release, even if the level
        # turns back before the end of the step.
        beyond_on = ls >= r + threshold_on
        beyond_off = ls <= r - threshold_off
        up = ~pending & ~beyond_off & ((lb >= r + threshold_on) | beyond_on)
        dn = ~pending & ~up & ((lb <= r - threshold_off) | beyond_off)
        target = jnp.where(up, r + threshold_on, r - threshold_off)
        tc = s + _safe_frac(target - ls, lb - ls) * (tb - s)
        tc = jnp.where(beyond_on | beyond_off, s, tc)
        fired = up | dn
        t_free = jnp.where(fired, tc + refractory_us, t_free)
        pending = pending | fired
        if reset_mode == "event":
            r = jnp.where(fired, target + eps, r)
        return (r, t_free, pending), (fired, tc, up)

    inputs = (log_i[:-1], log_i[1:], t_us[:-1], t_us[1:])
    if reference_noise is not None:
        inputs = inputs + (reference_noise,)
    state, out = jax.lax.scan(step, state, inputs)
    return out, state


def soft_event_counts(
    log_i: Float[Array, "t p"],
    t_us: Float[Array, " t"],
    threshold_on: Float[Array, " p"],
    threshold_off: Float[Array, " p"],
    refractory_us: Float[Array, ""],
    *,
    temperature: float | Float[Array, ""],
    state=None,
) -> tuple[Float[Array, "t1 p"], Float[Array, "t1 p"]]:
    """Expected ON and OFF event counts per time step, differentiable.

    The exact scan with every boolean replaced by a probability: firing is
    $\\mathrm{sigmoid}((\\log I - r - C)/τ)$ times the probability of being sensitive,
    release is $\\mathrm{sigmoid}((t_b - t_{free})/τ_t)$ with $τ_t = τ\\,Δt/C$, and the
    state is carried as expectations: the blind probability, the reference of the
    sensitive pixels and the release time of the blind ones. At `temperature → 0` this
    is :func:`exact_events_scan` (release mode), step for step.

    **Arguments:** as :func:`exact_events_scan`, plus `temperature` τ in log units
    (must be > 0; keep τ ≤ 0.01: every step of a flat trace still fires with
    probability sigmoid(−C/τ), which at τ = 0.05 adds tens of spurious expected events
    per sweep). `state` may be a soft state
    `(reference, release_time_us, pending_probability)`.

    **Returns:** `(on, off)` expected counts, each shape `(t-1, p)`, in [0, 1].
    """
    if state is None:
        r0, tf0, _ = initial_state(log_i[0])
        state = (r0, tf0, jnp.zeros_like(r0))
    c_mean = 0.5 * (threshold_on + threshold_off)

    def step(carry, inp):
        r, t_free, pend = carry
        la, lb, ta, tb = inp
        dt = tb - ta
        tau_t = temperature * dt / c_mean
        rel = pend * jax.nn.sigmoid((tb - t_free) / tau_t)
        f_rel = _safe_frac(t_free - ta, dt)
        l_rel = la + f_rel * (lb - la)
        # `r`, `s`, `ls` describe the *sensitive* pixels. The mass released now joins
        # them with its own reference (the level at release), weighted by its share
        # `w` of the sensitive mass; the blind mass's stale reference plays no part.
        sens = 1.0 - pend + rel
        ok_w = sens > 1e-12
        w = jnp.where(ok_w, rel / jnp.where(ok_w, sens, 1.0), 0.0)
        r = r + w * (l_rel - r)
        pend = pend - rel
        s = ta + w * f_rel * dt
        ls = la + w * (l_rel - la)
        up = sens * jax.nn.sigmoid((lb - r - threshold_on) / temperature)
        dn = (sens - up) * jax.nn.sigmoid((r - threshold_off - lb) / temperature)
        tc_up = s + _safe_frac(r + threshold_on - ls, lb - ls) * (tb - s)
        tc_dn = s + _safe_frac(r - threshold_off - ls, lb - ls) * (tb - s)
        # Release time of the blind mass, conditional on being blind: a mixture of the
        # still-blind pixels' old release time and the new events' ones.
        tot = pend + up + dn
        mixed = (
            pend * t_free + up * (tc_up + refractory_us) + dn * (tc_dn + refractory_us)
        )
        ok = tot > 1e-12
        t_free = jnp.where(ok, mixed / jnp.where(ok, tot, 1.0), t_free)
        pend = tot
        return (r, t_free, pend), (up, dn)

    inputs = (log_i[:-1], log_i[1:], t_us[:-1], t_us[1:])
    _, (on, off) = jax.lax.scan(step, state, inputs)
    return on, off


def photoreceptor_lowpass(
    log_i: Float[Array, "t p"],
    dt_us: Float[ArrayLike, ""],
    cutoff_hz: Float[ArrayLike, ""],
    log_eps: Float[ArrayLike, ""],
    sequential: bool = False,
) -> Float[Array, "t p"]:
    r"""The photoreceptor's first-order low-pass of the log-intensity, faster when
    brighter (v2e's model: the cut-off is proportional to the photocurrent).

    $y_j = a_j y_{j-1} + (1 - a_j) x_j$, $a_j = \exp(-2π f_c I_j Δt)$, with $x$ the
    log-intensity, $I_j = e^{x_j} - ε$ the intensity as a fraction of a white pixel's
    peak and $f_c$ the cut-off there (Hz). Exact for an input held constant over each
    step; a linear recurrence, so it runs as an associative scan. Starts settled
    ($y_0 = x_0$: the simulator's windows start in the dark part of the sweep).

    **Arguments:** `log_i` `(t, p)` on a uniform grid of step `dt_us` (µs); `cutoff_hz`;
    `log_eps` ε; `sequential`: a `lax.scan` over t instead of the associative scan
    (the same recurrence; for a short, narrow input whose derivatives are compiled —
    the calibration's chart traces — it compiles in a fraction of the time).

    **Returns:** the filtered log-intensity, `(t, p)`.
    """
    inten = jnp.maximum(jnp.exp(log_i) - log_eps, 0.0)
    a = jnp.exp(-2.0 * jnp.pi * cutoff_hz * 1e-6 * dt_us * inten)
    a = a.at[0].set(0.0)
    b = (1.0 - a) * log_i

    if sequential:

        def step(y, ab):
            y = ab[0] * y + ab[1]
            return y, y

        _, y = jax.lax.scan(step, jnp.zeros_like(b[0]), (a, b))
        return y

    def combine(left, right):
        a1, b1 = left
        a2, b2 = right
        return a1 * a2, a2 * b1 + b2

    _, y = jax.lax.associative_scan(combine, (a, b), axis=0)
    return y
