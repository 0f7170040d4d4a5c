"""The tape's gathered `cond` and `vmap` (`jaxrt.march.tape._gathered`): a replayed
branch evaluated only for the rays of a block (or their elements) where its predicate
holds, in batches, against the same branch evaluated for every ray (values and
gradients, float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from test_lane_rules import primitives

from jaxrt.march import tape

AXIS = "rays"


def _block(theta, x, live, entries, gather):
    """Per ray: `cond(live, fn, dead, x)` replayed from `entries`, over a block vmapped on
    AXIS; fn reads one march entry and closes over `theta` (unbatched, as the scene)."""

    def fn(x, live):  # equals `dead` where not live, as `tape.cond` requires
        t = tape.march(lambda: None)  # the recorded value of the branch's one march
        y = jnp.sin(theta[0] * x) * t + theta[1] * x ** 2
        return {"y": jnp.where(live, y, 0.0), "alive": live & (x > -10.0)}

    def dead(x, live):
        return {"y": jnp.zeros_like(x), "alive": jnp.zeros((), bool)}

    def one(x, live, entry):
        with tape.replaying([[entry]]):
            return tape.cond(live, fn, dead, x, live, gather=True)

    if not gather:
        return jax.vmap(one)(x, live, entries)
    with tape.gathering(AXIS, gather):
        return jax.vmap(one, axis_name=AXIS)(x, live, entries)


@pytest.mark.parametrize("n, gather, pattern", [
    (10, 4, "alternate"), (10, 4, "none"), (10, 4, "all"), (10, 16, "alternate"),
    (33, 8, "random"), (1, 8, "all")])
def test_gathered_cond_equals_the_branch_for_every_ray(n, gather, pattern):
    rng = np.random.default_rng(n + gather)
    x = jnp.asarray(rng.uniform(-1.0, 1.0, n))
    entries = jnp.asarray(rng.uniform(0.5, 2.0, n))
    live = {"alternate": np.arange(n) % 2 == 1, "none": np.zeros(n, bool),
            "all": np.ones(n, bool), "random": rng.uniform(size=n) < 0.3}[pattern]
    live = jnp.asarray(live)
    theta = jnp.asarray([1.3, -0.4])

    def loss(theta, x, gather):
        out = _block(theta, x, live, entries, gather)
        return jnp.sum(out["y"] * jnp.arange(1.0, n + 1.0)), out

    (ref, _), ref_grad = jax.value_and_grad(loss, (0, 1), has_aux=True)(theta, x, 0)
    (val, out), grad = jax.jit(jax.value_and_grad(loss, (0, 1), has_aux=True),
                               static_argnums=2)(theta, x, gather)
    np.testing.assert_array_equal(np.asarray(out["alive"]), np.asarray(live))
    np.testing.assert_allclose(float(val), float(ref), rtol=1e-14)
    for a, b in zip(grad, ref_grad):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-15)
    expected = np.where(np.asarray(live), np.sin(1.3 * np.asarray(x)) * np.asarray(entries)
                        - 0.4 * np.asarray(x) ** 2, 0.0)
    np.testing.assert_allclose(np.asarray(out["y"]), expected, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("n, m, gather", [(10, 3, 4), (7, 4, 32), (5, 2, 1)])
def test_gathered_vmap_equals_the_function_of_every_element(n, m, gather):
    """`tape.vmap(fn, gather=(live, dead))` over the m elements of each ray (a level of
    the ray tree: a ray's children), replayed with only the live elements computed."""
    rng = np.random.default_rng(n * m)
    x = jnp.asarray(rng.uniform(-1.0, 1.0, (n, m)))
    entries = jnp.asarray(rng.uniform(0.5, 2.0, (n, m)))
    live = jnp.asarray(rng.uniform(size=(n, m)) < 0.4)
    theta = jnp.asarray([0.7, 0.2])

    def loss(theta, x, gather):
        def fn(x, live):
            t = tape.march(lambda: None)
            return jnp.where(live, jnp.cos(theta[0] * x) * t + theta[1], 0.0)

        def dead(x, live):
            return jnp.zeros_like(x)

        def one(x, live, entry):
            with tape.replaying([[entry]]):  # the vmap: one entry, its march batched
                return tape.vmap(fn, (lambda x, live: live, dead))(x, live)

        if gather:
            with tape.gathering(AXIS, gather):
                y = jax.vmap(one, axis_name=AXIS)(x, live, entries)
        else:
            y = jax.vmap(one)(x, live, entries)
        return jnp.sum(y * jnp.arange(1.0, y.size + 1.0).reshape(y.shape)), y

    (ref, ref_y), ref_grad = jax.value_and_grad(loss, (0, 1), has_aux=True)(theta, x, 0)
    (val, y), grad = jax.value_and_grad(loss, (0, 1), has_aux=True)(theta, x, gather)
    x_, entries_ = np.asarray(x), np.asarray(entries)
    expected = np.where(np.asarray(live), np.cos(0.7 * x_) * entries_ + 0.2, 0.0)
    np.testing.assert_allclose(np.asarray(ref_y), expected, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(y), expected, rtol=1e-13)
    np.testing.assert_allclose(float(val), float(ref), rtol=1e-14)
    for a, b in zip(grad, ref_grad):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-15)


def test_gathered_cond_branches_per_batch():
    """The program runs the branch in a loop over batches behind a `cond` on one scalar
    per batch, not a select of both branches for every ray (what a per-ray cond becomes
    under vmap, and what the replay without gathering computes)."""
    n = 12
    live = jnp.arange(n) % 3 == 0
    jaxpr = jax.make_jaxpr(lambda t, x: _block(t, x, live, x, 4))(jnp.ones(2), jnp.ones(n))
    assert {"cond", "scan"} <= primitives(jaxpr.jaxpr)
    plain = jax.make_jaxpr(lambda t, x: _block(t, x, live, x, 0))(jnp.ones(2), jnp.ones(n))
    assert not {"cond", "scan"} & primitives(plain.jaxpr)

