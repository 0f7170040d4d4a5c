"""Small bounded searches shared by the marches (no gradient)."""

import jax
import jax.numpy as jnp

_INV_PHI = 0.6180339887498949


def repeat(n, body, init):
    """`body(i, state)` n times: a while loop with a static bound (a fori_loop would
    lower to `scan`, which the lane-wise kernels of `jaxrt.kernels` do not run)."""
    def step(s):
        i, state = s
        return i + 1, body(i, state)

    return jax.lax.while_loop(lambda s: s[0] < n, step, (jnp.zeros((), jnp.int32), init))[1]


def golden_section(f, a, b, steps, t0=None):
    """(t, f(t)): golden-section search for a minimum of f on [a, b], `steps` evaluations
    after the first two (the bracket shrinks by 0.618 per step); with `t0`, also f(t0):
    (t, f(t), f(t0)).

    One loop (`repeat`) whose every iteration evaluates f once, at the point its index
    chooses: t0 (if given), the two interior points x1 = b − 0.618 (b − a) and
    x2 = a + 0.618 (b − a), then one new point per step; so the program holds one copy
    of f whatever `steps`.
    """
    extra = 0 if t0 is None else 1

    def body(i, s):
        a, b, x1, f1, x2, f2, f0 = s
        left = f1 < f2  # the minimum lies in [a, x2]
        a_new = jnp.where(left, a, x1)
        b_new = jnp.where(left, x2, b)
        x = jnp.where(left, b_new - _INV_PHI * (b_new - a_new), a_new + _INV_PHI * (b_new - a_new))
        k = i - extra  # 0, 1: the interior points; ≥ 2: the steps
        point = jnp.where(k == 0, x1, jnp.where(k == 1, x2, x))
        if extra:
            point = jnp.where(i == 0, t0, point)
        fx = f(point)
        stepping = k >= 2
        new = (jnp.where(stepping, a_new, a), jnp.where(stepping, b_new, b),
               jnp.where(stepping, jnp.where(left, x, x2), x1),
               jnp.where(stepping, jnp.where(left, fx, f2), jnp.where(k == 0, fx, f1)),
               jnp.where(stepping, jnp.where(left, x1, x), x2),
               jnp.where(stepping, jnp.where(left, f1, fx), jnp.where(k == 1, fx, f2)),
               jnp.where(i == 0, fx, f0) if extra else f0)
        return new

    x1 = b - _INV_PHI * (b - a)
    x2 = a + _INV_PHI * (b - a)
    zero = jnp.zeros_like(x1)
    _, _, x1, f1, x2, f2, f0 = repeat(steps + 2 + extra, body, (a, b, x1, zero, x2, zero, zero))
    found = jnp.where(f1 < f2, x1, x2), jnp.minimum(f1, f2)
    return found if t0 is None else found + (f0,)
