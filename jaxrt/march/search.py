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


def golden_section(f, a, b, steps):
    """(t, f(t)): golden-section search for a minimum of f on [a, b], `steps` evaluations
    after the first two (the bracket shrinks by 0.618 per step)."""

    def body(_, s):
        a, b, x1, f1, x2, f2 = s
        left = f1 < f2  # the minimum lies in [a, x2]
        a_new = jnp.where(left, a, x1)
        b_new = jnp.where(left, x2, b)
        x = jnp.where(left, b_new - _INV_PHI * (b_new - a_new), a_new + _INV_PHI * (b_new - a_new))
        fx = f(x)
        return (a_new, b_new, jnp.where(left, x, x2), jnp.where(left, fx, f2),
                jnp.where(left, x1, x), jnp.where(left, f1, fx))

    x1 = b - _INV_PHI * (b - a)
    x2 = a + _INV_PHI * (b - a)
    _, _, x1, f1, x2, f2 = repeat(steps, body, (a, b, x1, f(x1), x2, f(x2)))
    return jnp.where(f1 < f2, x1, x2), jnp.minimum(f1, f2)
