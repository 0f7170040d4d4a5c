"""Shared test problems: independent numpy references and small scenes.

The reference distances here are written from geometry (closest points, 2-D distances
to the profile of a solid of revolution, a root of the ellipsoid's Lagrange condition),
not from the formulas in `jaxrt.sdf`, so that the tests compare two derivations.
"""

import contextlib
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as jr
from jaxrt import sdf

# --------------------------------------------------------------------- geometry (numpy)


def rotation_matrix(axis, angle_deg):
    """Right-handed rotation by `angle_deg` about `axis`: I + sin θ K + (1 − cos θ) K²."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    th = np.radians(angle_deg)
    return np.eye(3) + np.sin(th) * k + (1.0 - np.cos(th)) * k @ k


def quaternion_matrix(q):
    """Rotation matrix of the unit quaternion q = (w, x, y, z) (Shoemake's formula)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def segment_distance_2d(q, a, b):
    """Distance from 2-D points q [N, 2] to the segment a–b."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    s = np.clip(((q - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(q - (a + s[:, None] * ab), axis=1)


def point_in_polygon(q, vertices):
    """Inside test for 2-D points q [N, 2] and a convex polygon listed counter-clockwise."""
    v = np.asarray(vertices, float)
    inside = np.ones(len(q), bool)
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        cross = (b[0] - a[0]) * (q[:, 1] - a[1]) - (b[1] - a[1]) * (q[:, 0] - a[0])
        inside &= cross > 0.0
    return inside


def revolved_distance(p, polygon, surface_edges):
    """Signed distance to the solid of revolution about y of a convex profile polygon.

    The profile lives in the (r, y) half-plane, r = |p.xz|; `surface_edges` are the
    polygon's edges (index pairs) that are surfaces of the solid (not those on the
    axis r = 0, which lie inside it). The distance to the solid is the 2-D distance to
    those edges, negative inside the polygon.
    """
    q = np.stack([np.hypot(p[:, 0], p[:, 2]), p[:, 1]], axis=1)
    d = np.min([segment_distance_2d(q, polygon[i], polygon[j]) for i, j in surface_edges], axis=0)
    return np.where(point_in_polygon(q, polygon), -d, d)


def ref_sphere(p, radius):
    return np.linalg.norm(p, axis=1) - radius


def ref_plane(p, normal, offset):
    n = np.asarray(normal, float)
    return p @ (n / np.linalg.norm(n)) - offset


def ref_box(p, half_extents):
    """Outside: distance to the closest point (clamp); inside: −(distance to nearest face)."""
    h = np.asarray(half_extents, float)
    closest = np.clip(p, -h, h)
    outside = np.linalg.norm(p - closest, axis=1)
    inside = np.min(h - np.abs(p), axis=1)
    is_in = np.all(np.abs(p) < h, axis=1)
    return np.where(is_in, -inside, outside)


def ref_round_box(p, half_extents, radius):
    """The box shrunk by `radius` (signed distance to it) minus `radius`."""
    return ref_box(p, np.asarray(half_extents, float) - radius) - radius


def ref_torus(p, major, minor):
    """Distance to the core circle (radius `major` in the xz plane) minus `minor`."""
    rxz = np.hypot(p[:, 0], p[:, 2])
    closest = np.stack([major * p[:, 0] / rxz, np.zeros(len(p)), major * p[:, 2] / rxz], axis=1)
    return np.linalg.norm(p - closest, axis=1) - minor


def ref_cone(p, radius, height):
    """Profile triangle (0, 0), (R, 0), (0, H): base edge and slanted edge are surfaces."""
    poly = [(0.0, 0.0), (radius, 0.0), (0.0, height)]
    return revolved_distance(p, poly, [(0, 1), (1, 2)])


def ref_cylinder(p, radius, half_height):
    """Profile rectangle [0, R] × [−h, h]: bottom, side and top are surfaces."""
    poly = [(0.0, -half_height), (radius, -half_height), (radius, half_height), (0.0, half_height)]
    return revolved_distance(p, poly, [(0, 1), (1, 2), (2, 3)])


def ref_capsule(p, half_height, radius):
    """3-D distance to the segment from (0, −h, 0) to (0, h, 0) minus the radius."""
    a, b = np.array([0.0, -half_height, 0.0]), np.array([0.0, half_height, 0.0])
    s = np.clip(((p - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[:, None] * (b - a)), axis=1) - radius


def ref_ellipsoid(p, radii, iterations=200):
    """Exact signed distance to an ellipsoid by bisection on the Lagrange multiplier.

    The closest point is x_i = r_i² p_i / (λ + r_i²) with Σ (r_i p_i / (λ + r_i²))² = 1;
    the left side decreases in λ on (−min r², ∞), so the root is unique.
    """
    r2 = np.asarray(radii, float) ** 2
    rr = np.sqrt(r2)
    lo = np.full(len(p), -r2.min() * (1.0 - 1e-15))
    hi = np.full(len(p), 1e3)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        g = np.sum((rr * p / (mid[:, None] + r2)) ** 2, axis=1) - 1.0
        lo, hi = np.where(g > 0.0, mid, lo), np.where(g > 0.0, hi, mid)
    x = r2 * p / (lo[:, None] + r2)
    d = np.linalg.norm(p - x, axis=1)
    return np.where(np.sum((p / rr) ** 2, axis=1) > 1.0, d, -d)


def circle_distance(p, center, normal, radius):
    """Distance from points p [N, 3] to a circle in 3-D (centre, unit normal, radius)."""
    v = p - center
    axial = v @ normal
    radial = v - axial[:, None] * normal
    rho = np.linalg.norm(radial, axis=1)
    return np.hypot(rho - radius, axial)


def cap_distance(p, c, r, keep):
    """Distance from p to the part of the sphere (c, r) whose points satisfy `keep`.

    `keep(x)` is a boolean test on surface points [N, 3]. The kept part must be a
    spherical cap bounded by the circle where the sphere meets another sphere, given
    as `keep.rim = (centre, normal, radius)`. The distance to a cap is the distance to
    the radial projection of p when that lies in the cap, else to the rim (distance
    along the sphere grows with the geodesic angle from the projection).
    """
    v = p - c
    proj = c + r * v / np.linalg.norm(v, axis=1, keepdims=True)
    radial = np.abs(np.linalg.norm(v, axis=1) - r)
    return np.where(keep(proj), radial, circle_distance(p, *keep.rim))


def two_sphere_rim(c1, r1, c2, r2):
    """The circle where spheres (c1, r1) and (c2, r2) meet: (centre, unit normal, radius)."""
    axis = c2 - c1
    dist = np.linalg.norm(axis)
    n = axis / dist
    a = (dist * dist + r1 * r1 - r2 * r2) / (2.0 * dist)
    return c1 + a * n, n, np.sqrt(r1 * r1 - a * a)


def two_sphere_boolean(p, c1, r1, c2, r2, op):
    """Exact signed distance to the union/intersection/subtraction of two balls.

    The boundary is made of spherical caps: for "union", the part of each sphere
    outside the other ball; "intersection", the part of each inside the other;
    "subtraction" (ball 1 minus ball 2), sphere 1 outside ball 2 and sphere 2 inside
    ball 1. The sign comes from the point-set definition.
    """
    rim = two_sphere_rim(c1, r1, c2, r2)
    in1 = lambda x: np.linalg.norm(x - c1, axis=1) < r1  # noqa: E731
    in2 = lambda x: np.linalg.norm(x - c2, axis=1) < r2  # noqa: E731

    def part(test):
        test.rim = rim
        return test

    if op == "union":
        k1, k2 = part(lambda x: ~in2(x)), part(lambda x: ~in1(x))
        inside = in1(p) | in2(p)
    elif op == "intersection":
        k1, k2 = part(in2), part(in1)
        inside = in1(p) & in2(p)
    else:
        k1, k2 = part(lambda x: ~in2(x)), part(in1)
        inside = in1(p) & ~in2(p)
    d = np.minimum(cap_distance(p, c1, r1, k1), cap_distance(p, c2, r2, k2))
    return np.where(inside, -d, d)


# --------------------------------------------------------------------- jax helpers


@eqx.filter_jit
def _values(node, p):
    return jax.vmap(node)(p)


@eqx.filter_jit
def _grad_norms(node, p):
    return jnp.linalg.norm(jax.vmap(jax.grad(lambda q: node(q)))(p), axis=-1)


@eqx.filter_jit
def _materials(node, p):
    return jax.vmap(lambda q: node.eval(q)[1])(p)


def batch(node):
    """`node` mapped over points [N, 3] -> distances [N] (numpy; compiled once per
    node structure)."""
    return lambda p: np.asarray(_values(node, jnp.asarray(p)))


def grad_norms(node, p):
    """|∇f| at points p [N, 3] (autodiff)."""
    return np.asarray(_grad_norms(node, jnp.asarray(p)))


def materials_of(node, p):
    """Material indices at points p [N, 3]."""
    return np.asarray(_materials(node, jnp.asarray(p)))


def to_dtype(tree, dtype):
    """Cast the float arrays of a pytree (a scene node, a camera) to `dtype`."""
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)
        else x, tree)


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_directions(rng, n):
    return unit(rng.normal(size=(n, 3)))


@eqx.filter_jit
def _along(node, origins, directions, ts):
    return jax.vmap(lambda o, d: jax.vmap(lambda t: node(o + t * d))(ts))(origins, directions)


def first_crossing(node, origins, directions, t_max, samples, inside=False):
    """Brute-force reference for sphere tracing: the first t on a uniform grid of
    `samples` points in [0, t_max] where f ≤ 0 (f ≥ 0 for rays that start `inside`;
    inf if none), and the grid step."""
    ts = np.linspace(0.0, t_max, samples)
    f = np.asarray(_along(node, jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(ts)))
    crossed = f >= 0.0 if inside else f <= 0.0
    first = np.argmax(crossed, axis=1)
    return np.where(crossed.any(axis=1), ts[first], np.inf), ts[1] - ts[0]


# --------------------------------------------------------------------- small scenes


def inside_sphere_scene(albedo, radius=1.0, center=(0.0, 0.0, 0.0)):
    """A Lambert sphere seen from inside, lit by a point light of intensity π at its
    centre: every visible point has radiance albedo · (π / r²) · cos 0 / π = albedo / r²."""
    return jr.Scene(
        surface=sdf.Translate(sdf.Sphere(radius), offset=center),
        materials=[jr.bsdf.Lambert(albedo)],
        lights=[jr.PointLight(position=center, intensity=(np.pi, np.pi, np.pi))],
        background=(7.0, 7.0, 7.0),  # any ray that escapes shows up
    )


def cluttered_scene():
    """A sphere on a plane beside a twisted box: two materials, both light kinds."""
    surface = sdf.Union(
        sdf.Translate(sdf.Sphere(1.0, material=0), offset=(0.0, 1.0, 0.0)),
        sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1),
        sdf.Translate(sdf.Twist(sdf.Box((0.3, 0.8, 0.3), material=1), rate=2.0, radius=0.5),
                      offset=(1.8, 0.8, 0.0)),
    )
    return jr.Scene(
        surface=surface,
        materials=[jr.bsdf.Lambert((0.7, 0.6, 0.5)), jr.bsdf.Lambert((0.2, 0.5, 0.8))],
        lights=[jr.PointLight((2.0, 4.0, -3.0), (50.0, 50.0, 50.0)),
                jr.DirectionalLight((0.3, 1.0, -0.2), (1.0, 1.0, 1.0))],
        background=(0.05, 0.05, 0.08),
    )


@contextlib.contextmanager
def warnings_as_errors():
    """Every warning raised as an error, but JAX's own deprecation of its Pallas Triton
    backend (jax 0.11; the GPU kernel uses it until it moves to Mosaic GPU)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message="The Pallas Triton backend is deprecated",
                                category=DeprecationWarning)
        yield
