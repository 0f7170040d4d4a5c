"""Bounding balls (`SDF.bounding_ball`) and the union's skipping of far children
(`sdf.stack.culled_eval`): every ball bounds its node's value from below outside it, and
a union that skips children is the same function as one that evaluates them all."""

import contextlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import config, sdf
from jaxrt.march import tape
from jaxrt.sdf import stack

SHOWCASE = config.load(Path(__file__).resolve().parents[1] / "jaxrt" / "data" / "showcase.toml")[0]

NODES = {
    "box": sdf.Box((1.0, 0.5, 0.25)),
    "round_box": sdf.RoundBox((1.0, 0.6, 0.4), 0.15),
    "torus": sdf.Torus(1.0, 0.3),
    "cone": sdf.Cone(0.7, 1.3),
    "flat_cone": sdf.Cone(1.5, 0.4),
    "capsule": sdf.Capsule(0.6, 0.3),
    "cylinder": sdf.Cylinder(0.5, 0.8),
    "ellipsoid": sdf.Ellipsoid((1.0, 0.3, 0.5)),
    "rotate": sdf.Rotate(sdf.Translate(sdf.Box((0.3, 0.6, 0.2)), (0.5, 0.2, 0.0)), (1.0, 2.0, 0.5), 40.0),
    "transform": sdf.Transform(sdf.Translate(sdf.Torus(0.5, 0.1), (0.3, 0.0, 0.4)),
                               np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                               (0.2, -0.5, 1.0)),
    "scale": sdf.Scale(sdf.Translate(sdf.Capsule(0.4, 0.2), (0.4, 0.0, 0.0)), 1.7),
    "repeat": sdf.Repeat(sdf.Translate(sdf.Sphere(0.2), (0.1, 0.05, 0.0)), (0.7, 0.0, 0.5), (2, 0, 1)),
    "union": sdf.Union(sdf.Translate(sdf.Box((0.2, 0.3, 0.4)), (1.0, 0.0, 0.0)),
                       sdf.Translate(sdf.Ellipsoid((0.5, 0.2, 0.2)), (-1.0, 0.5, 0.0))),
    "intersection": sdf.Intersection(sdf.Sphere(0.8), sdf.Translate(sdf.Box((0.6, 0.6, 0.6)), (0.3, 0, 0))),
    "subtraction": sdf.Subtraction(sdf.Box((0.7, 0.7, 0.7)), sdf.Sphere(0.9)),
    "smooth_union": sdf.SmoothUnion(sdf.Translate(sdf.Sphere(0.5), (-0.6, 0.0, 0.0)),
                                    sdf.Translate(sdf.Ellipsoid((0.3, 0.6, 0.3)), (0.4, 0.3, 0.0)), 0.5),
    "smooth_subtraction": sdf.SmoothSubtraction(sdf.Sphere(0.6), sdf.Translate(sdf.Sphere(0.3), (0.4, 0, 0)), 0.2),
    "smooth_intersection": sdf.SmoothIntersection(sdf.Box((0.45, 0.45, 0.45)), sdf.Sphere(0.55), 0.3),
    "twist": sdf.Twist(sdf.Translate(sdf.Box((0.4, 0.9, 0.4)), (0.3, 0.0, 0.2)), 1.6, 1.0),
    "bend": sdf.Bend(sdf.Translate(sdf.Box((1.8, 0.45, 0.6)), (0.0, 0.4, 0.0)), 0.6, 2.0),
    "displace": sdf.Displace(sdf.Sphere(0.7), amplitude=0.2),
    "showcase_children": sdf.Union(*SHOWCASE.surface.children_[1:]),
}


@pytest.mark.parametrize("name", sorted(NODES))
def test_a_bounding_ball_bounds_the_value_from_below_outside_it(name):
    """f(p) ≥ w (|p − c| − r) at points outside the ball, from its surface to 8 radii
    away (float64)."""
    node = NODES[name]
    centre, radius, weight = (np.asarray(x, np.float64) for x in node.bounding_ball())
    assert 0.0 < weight <= 1.0 and radius > 0.0
    rng = np.random.default_rng(len(name))
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    gap = radius * np.concatenate([np.full(400, 1e-9), rng.uniform(0.0, 8.0, 3600)])
    p = centre + u * (radius + gap)[:, None]
    f = np.asarray(jax.vmap(node)(jnp.asarray(p)))
    bound = weight * (np.linalg.norm(p - centre, axis=1) - radius)
    assert np.all(f >= bound - 1e-12 * (1.0 + np.abs(bound))), (f - bound).min()


def test_a_plane_and_an_infinite_repetition_have_no_ball():
    assert sdf.Plane().bounding_ball() is None
    assert sdf.Repeat(sdf.Sphere(0.2), (1.0, 1.0, 1.0)).bounding_ball() is None
    assert sdf.Union(sdf.Plane(), sdf.Sphere(1.0)).bounding_ball() is None


def _union_on_lanes(surface, points):
    """The union evaluated as "fused" traces it (skipping far children) and as the
    vmapped path does, under one jit each."""
    def run(skipping, p):
        with tape.lanes("fused" if skipping else None), tape.stepping():
            return jax.vmap(surface.eval)(p)

    skip = jax.jit(lambda p: run(True, p))(points)
    full = jax.jit(lambda p: run(False, p))(points)
    return skip, full


def test_a_union_that_skips_far_children_is_the_same_function():
    """The showcase's union (planes, placements, booleans, deformations) and a group of
    stacked boxes, at points near and far: distances to rounding and materials equal,
    with children skipped (`cond` in the program) where a long march's loop is traced
    for "fused"."""
    boxes = sdf.Union(sdf.Plane(), *[sdf.Translate(sdf.Rotate(sdf.Box((0.2, 0.3, 0.1), material=i % 3),
                                                              (0.0, 1.0, 0.0), 10.0 * i),
                                                   (np.cos(i), 0.3, np.sin(i) * 2.0)) for i in range(9)])
    stacked = stack.prestack(boxes, balls=True)  # with the balls computed ahead, as render does
    assert isinstance(stacked, stack.StackedUnion) and stacked.balls[1] is not None
    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.uniform(-6.0, 6.0, (3000, 3)) * np.array([1.0, 0.4, 1.0]))
    ahead = stack.prestack(SHOWCASE.surface, balls=True)
    # all but the plane, 3 spheres and the rotated capsule (11 equations with its matrix
    # computed ahead: no dearer than the test)
    assert sum(b is not None for b in ahead.balls) == 13
    for surface in (SHOWCASE.surface, ahead, boxes, stacked):
        (d_skip, m_skip), (d_full, m_full) = _union_on_lanes(surface, p)
        np.testing.assert_allclose(d_skip, d_full, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(m_skip, m_full)

        def program(lanes, stepping):
            with tape.lanes(lanes), (tape.stepping() if stepping else contextlib.nullcontext()):
                return str(jax.make_jaxpr(surface.eval)(p[0]))
        # skipped in a long march's loop traced for "fused" only (not at a normal, say)
        assert "cond[" in program("fused", True)
        assert "cond[" not in program("fused", False) + program(None, True) + program("pallas", True)
