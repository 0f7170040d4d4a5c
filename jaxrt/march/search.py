"""Small bounded searches shared by the marches (no gradient)."""

import jax
import jax.numpy as jnp

from . import form

_INV_PHI = 0.6180339887498949


def repeat(n, body, init):
    """`body(i, state)` n times: a while loop with a static bound (a fori_loop would
    lower to `scan`, which the lane-wise kernels of `jaxrt.kernels` do not run). In the
    "plain" form (`jaxrt.march.form`) a loop of at most `form.PLAIN_UNROLL` iterations
    is straight code instead, `i` a Python int."""
    if form.current() == "plain" and n <= form.PLAIN_UNROLL:
        state = init
        for i in range(n):
            state = body(i, state)
        return state

    def step(s):
        i, state = s
        return i + 1, body(i, state)

    return jax.lax.while_loop(lambda s: s[0] < n, step, (jnp.zeros((), jnp.int32), init))[1]


def golden_section(f, a, b, steps, t0=None):
    """(t, f(t)): golden-section search for a minimum of f on [a, b], `steps` evaluations
    after the first two (the bracket shrinks by 0.618 per step); with `t0`, also f(t0):
    (t, f(t), f(t0)). In the "plain" form (`jaxrt.march.form`): `golden_plain`.

    One loop (`repeat`) whose every iteration evaluates f once, at the point its index
    chooses: t0 (if given), the two interior points x1 = b − 0.618 (b − a) and
    x2 = a + 0.618 (b − a), then one new point per step; so the program holds one copy
    of f whatever `steps`.
    """
    if form.current() == "plain":
        return golden_plain(f, a, b, steps, t0)
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


def golden_plain(f, a, b, steps, t0=None, aux=False):
    """`golden_section` in the "plain" form: f(t0), f(x1) and f(x2) before the loop,
    whose every iteration is one golden-section step (three copies of f, four with t0;
    no select on an iteration index). With `aux`, f returns (value, extra) and the
    extra of the point found is returned after its value: (t, f(t), extra[, f(t0)])."""
    def value(x):
        out = f(x)
        return out if aux else (out, jnp.zeros((), jnp.asarray(x).dtype))

    def body(_, s):
        a, b, x1, f1, e1, x2, f2, e2 = s
        left = f1 < f2  # the minimum lies in [a, x2]
        a_new = jnp.where(left, a, x1)
        b_new = jnp.where(left, x2, b)
        x = jnp.where(left, b_new - _INV_PHI * (b_new - a_new), a_new + _INV_PHI * (b_new - a_new))
        fx, ex = value(x)
        return (a_new, b_new, jnp.where(left, x, x2), jnp.where(left, fx, f2),
                jnp.where(left, ex, e2), jnp.where(left, x1, x), jnp.where(left, f1, fx),
                jnp.where(left, e1, ex))

    x1 = b - _INV_PHI * (b - a)
    x2 = a + _INV_PHI * (b - a)
    first = (a, b, x1) + value(x1) + (x2,) + value(x2)
    _, _, x1, f1, e1, x2, f2, e2 = repeat(steps, body, first)
    left = f1 < f2
    found = jnp.where(left, x1, x2), jnp.minimum(f1, f2)
    if aux:
        found += (jnp.where(left, e1, e2),)
    return found if t0 is None else found + (value(t0)[0],)
