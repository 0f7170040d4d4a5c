"""A free-form shape: signed distances sampled on a dense voxel grid.

`Grid` interpolates samples φ_ijk of a signed distance at the vertices

    x_ijk = lower + (i, j, k) · h,   h = (upper − lower) / (n − 1),   n = (nx, ny, nz),

of an axis-aligned box trilinearly (the vertices include the box's faces, as
`heightfield.GridHeight` does in 2-D). Outside the box its value is the distance to
the box plus the interpolant at the nearest box point c(p) = clamp(p, lower, upper),

    f(p) = |p − c(p)| + φ(c(p)),

so a ray from outside marches straight to the box and the shape inside is unchanged.
Every sample is a differentiable leaf: image losses reach the eight samples around a
hit point (and around its normal's cell) through the implicit-function hit and the
autodiff normal; an optimiser moves them (experiments/inverse/freeform.py), `upsample`
refines the grid coarse-to-fine, `redistance` keeps the samples a distance field and
`eikonal_loss` penalises |∇φ| ≠ 1.

Lipschitz bound (what the sphere tracer divides its steps by). Inside a cell the
trilinear gradient's x component is a bilinear blend of the cell's four x-edge slopes
(φ_{i+1,·,·} − φ_{i,·,·}) / h_x, so |∂f/∂x| ≤ M_x, the largest of them, and likewise
for y and z: |∇f| ≤ sqrt(M_x² + M_y² + M_z²) in that cell; f is continuous, so the
largest such per-cell bound, L_in, bounds it over the box. (A grid whose neighbouring
samples differ by at most h·L anywhere is L·sqrt(3)-Lipschitz at worst; the per-cell
bound is ≈ 1 for a sampled distance field, whose gradient barely turns within a cell.)
Outside the box the gradient of |p − c| (a unit vector along the clamped axes) is
orthogonal to that of φ(c(p)) (along the free axes, tangential to the box), so
|∇f|² = 1 + |∇_t φ|² ≤ 1 + L_face², L_face the largest per-cell bound of the
tangential slopes on the six faces. `lipschitz()` = max(L_in, sqrt(1 + L_face²)),
computed from the samples under `stop_gradient`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..vecmath import safe_norm
from .base import Primitive, as_float, check_sdf, material_index


class Grid(Primitive):
    """Signed distances `values` [nx, ny, nz] (each n ≥ 2) at the vertices of the box
    [lower, upper], interpolated trilinearly; outside, the distance to the box plus the
    value at the nearest box point (module docstring). A bound, exact where the samples
    are those of a plane; for a sampled distance field the error is O(h²) where the
    field is smooth. Shading is faceted at cell faces, where the trilinear gradient
    jumps.

    Differentiable: `values` (every sample), `lower`, `upper`.
    """

    values: jnp.ndarray
    lower: jnp.ndarray
    upper: jnp.ndarray

    def __init__(self, values, lower=(-1.0, -1.0, -1.0), upper=(1.0, 1.0, 1.0), material=0):
        if isinstance(values, jax.core.Tracer):
            v = values
        else:
            try:
                v = jnp.asarray(values, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"`Grid(values=...)` must be an array of numbers, got {type(values).__name__}") from None
            if v.ndim != 3 or min(v.shape) < 2:
                raise ValueError(f"`Grid(values=...)` must have shape [nx, ny, nz] with every n ≥ 2, got {v.shape}")
            if not np.all(np.isfinite(np.asarray(v))):
                raise ValueError("`Grid(values=...)` must be finite (it has NaN or inf samples)")
        self.values = v
        self.lower = as_float(lower, (3,), "Grid(lower=...)")
        self.upper = as_float(upper, (3,), "Grid(upper=...)")
        if not isinstance(self.lower, jax.core.Tracer) and not isinstance(self.upper, jax.core.Tracer):
            lo, hi = np.asarray(self.lower), np.asarray(self.upper)
            if not np.all(lo < hi):
                raise ValueError(f"`Grid(lower=..., upper=...)` must have lower < upper on every axis, got {lo.tolist()} and {hi.tolist()}")
        self.material = material_index(material, "Grid(material=...)")

    @property
    def resolution(self):
        """(nx, ny, nz), static."""
        return tuple(self.values.shape)

    def spacing(self):
        """h = (upper − lower) / (n − 1), [3]."""
        return (self.upper - self.lower) / (jnp.asarray(self.values.shape, self.upper.dtype) - 1.0)

    def points(self):
        """The vertex positions x_ijk, [nx, ny, nz, 3]."""
        return vertices(self.lower, self.upper, self.values.shape)

    def interpolate(self, p):
        """Trilinear interpolation of the samples at p ([3], clamped into the box)."""
        n = jnp.asarray(self.values.shape, p.dtype)
        u = (p - self.lower) / (self.upper - self.lower) * (n - 1.0)
        u = jnp.where(u < 0.0, 0.0, jnp.where(u > n - 1.0, n - 1.0, u))  # selects: see `distance`
        i = jnp.clip(jnp.floor(jax.lax.stop_gradient(u)).astype(jnp.int32), 0,
                     jnp.asarray(self.values.shape, jnp.int32) - 2)
        w = u - i  # [3] fractions in the cell
        c = jax.lax.dynamic_slice(self.values, (i[0], i[1], i[2]), (2, 2, 2))
        cx = c[0] * (1.0 - w[0]) + c[1] * w[0]          # [2, 2] over (y, z)
        cy = cx[0] * (1.0 - w[1]) + cx[1] * w[1]        # [2] over z
        return cy[0] * (1.0 - w[2]) + cy[1] * w[2]

    def distance(self, p):
        # c(p) by selects, not jnp.clip: on a face (p = c) the gradient is the
        # interpolant's, where clip's tie rule would halve it.
        c = jnp.where(p < self.lower, self.lower, jnp.where(p > self.upper, self.upper, p))
        return safe_norm(p - c) + self.interpolate(c)

    def lipschitz(self):
        v = jax.lax.stop_gradient(self.values)
        h = jax.lax.stop_gradient(self.spacing()).astype(v.dtype)
        inside = jnp.max(_cell_gradient_bound(v, h))
        faces = []
        for axis in range(3):
            others = [a for a in range(3) if a != axis]
            for index in (0, v.shape[axis] - 1):
                face = jnp.take(v, index, axis=axis)
                faces.append(jnp.max(_cell_gradient_bound(face, h[jnp.array(others)])))
        tangential = jnp.max(jnp.stack(faces))
        return jnp.maximum(inside, jnp.sqrt(1.0 + tangential * tangential))

    @classmethod
    def from_sdf(cls, node, lower, upper, resolution, material=None):
        """A grid of `node`'s signed distances at the vertices of [lower, upper].

        `resolution`: n (every axis) or (nx, ny, nz), each ≥ 2. `material`: default the
        smallest material index of `node`. Differentiable with respect to `node`'s
        parameters (the samples are `node`'s values).
        """
        check_sdf(node, "Grid.from_sdf(node=...)")
        shape = _resolution(resolution, "Grid.from_sdf(resolution=...)")
        lower = as_float(lower, (3,), "Grid.from_sdf(lower=...)")
        upper = as_float(upper, (3,), "Grid.from_sdf(upper=...)")
        x = vertices(lower, upper, shape)
        values = jax.vmap(node)(x.reshape(-1, 3)).reshape(shape)
        if material is None:
            ids = node.material_ids()
            material = min(ids) if ids else 0
        return cls(values, lower, upper, material)


def vertices(lower, upper, shape):
    """Vertex positions lower + (i, j, k)·h of a grid of `shape` over [lower, upper]."""
    axes = [jnp.linspace(lower[a], upper[a], shape[a]) for a in range(3)]
    return jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1)


def _resolution(resolution, name):
    if isinstance(resolution, (int, np.integer)) and not isinstance(resolution, bool):
        resolution = (int(resolution),) * 3
    try:
        shape = tuple(int(r) for r in resolution)
        ok = len(shape) == 3 and all(r >= 2 and r == q for r, q in zip(shape, resolution))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"`{name}` must be an integer ≥ 2 or three of them, got {resolution!r}")
    return shape


def _cell_gradient_bound(v, h):
    """Per-cell bound sqrt(Σ_a M_a²) on |∇| of the multilinear interpolant of the
    samples `v` (any number of axes), M_a the largest |slope| of the cell's edges along
    axis a (module docstring). Shape: the cells, n − 1 per axis."""
    total = 0.0
    for a in range(v.ndim):
        s = jnp.abs(jnp.diff(v, axis=a)) / h[a]
        for b in range(v.ndim):  # the cell's edges along a: both ends along every other axis
            if b != a:
                s = jnp.maximum(jax.lax.slice_in_dim(s, 0, s.shape[b] - 1, axis=b),
                                jax.lax.slice_in_dim(s, 1, s.shape[b], axis=b))
        total = total + s * s
    return jnp.sqrt(total)


# -- helpers for fitting -----------------------------------------------------------------


def resample(grid, resolution):
    """`grid`'s interpolant sampled at the vertices of a grid of `resolution` over the
    same box (a new `Grid`)."""
    shape = _resolution(resolution, "resample(resolution=...)")
    x = vertices(grid.lower, grid.upper, shape)
    values = jax.vmap(grid.interpolate)(x.reshape(-1, 3)).reshape(shape)
    return Grid(values, grid.lower, grid.upper, grid.material)


def upsample(grid, factor=2, resolution=None):
    """A finer grid with the same interpolated shape, for coarse-to-fine fits.

    With an integer `factor` the new resolution is (n − 1)·factor + 1, so every old
    vertex is a new vertex (the interpolant is preserved there, and everywhere along the
    old grid's edges); or give `resolution` (n or (nx, ny, nz)) to resample freely.
    """
    if resolution is None:
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise ValueError(f"`upsample(factor=...)` must be an integer ≥ 1, got {factor!r}")
        resolution = tuple((n - 1) * int(factor) + 1 for n in grid.values.shape)
    return resample(grid, resolution)


def redistance(grid, iterations=None):
    """`grid` with its samples replaced by signed distances to the zero level set of
    its samples (a new `Grid`; no gradient is meant to flow through it: call it between
    optimiser steps).

    1. Vertices next to the surface (a 6-neighbour of opposite sign) get the distance
       to the plane through the surface's crossings of their edges (linear along each
       edge, as the interpolant is), or |φ| / |∇φ| (central differences) where that
       is smaller: exact for a linear field, the same for s·φ and φ (s > 0), and never
       more than one cell, so no steep cell is created.
    2. The others get the Godunov upwind solution of the eikonal equation |∇u| = 1
       (Zhao 2005, "A fast sweeping method for eikonal equations"), updated all at
       once (Jacobi) `iterations` times (default: the largest n, which lets the front
       cross the grid), u ← min(u, solution from the 6 neighbours); the vertices of
       step 1 stay fixed. First-order accurate away from the surface.
    3. The sign of the original samples is kept.
    """
    iterations = max(grid.values.shape) if iterations is None else int(iterations)
    values = _redistance(grid.values, grid.spacing().astype(grid.values.dtype), iterations)
    return Grid(values, grid.lower, grid.upper, grid.material)


@eqx.filter_jit
def _redistance(v, h, iterations):
    """The samples of `redistance` from samples v [nx, ny, nz] and spacings h [3]."""
    sign = jnp.where(v < 0.0, -1.0, 1.0).astype(v.dtype)
    # Distance to the surface along each axis: the linear crossing on an edge whose
    # ends differ in sign, s = h |φ_i| / (|φ_i| + |φ_j|) (the nearer of the two edges);
    # the vertex's distance is that to the plane through the crossings,
    # d0 = (Σ_axes 1 / s_a²)^(−1/2), exact for a linear field and ≤ min_a s_a ≤ h.
    a_v = jnp.abs(v)
    inv2 = jnp.zeros(v.shape, v.dtype)
    near = jnp.zeros(v.shape, bool)
    for a in range(3):
        pad = jnp.pad(v, [(1, 1) if b == a else (0, 0) for b in range(3)], mode="edge")
        s_a = None
        for nb in (jax.lax.slice_in_dim(pad, 0, v.shape[a], axis=a),
                   jax.lax.slice_in_dim(pad, 2, v.shape[a] + 2, axis=a)):
            cross = (sign * jnp.where(nb < 0.0, -1.0, 1.0) < 0.0) | (v == 0.0)
            s = jnp.where(cross, h[a] * a_v / jnp.maximum(a_v + jnp.abs(nb), 1e-30), jnp.inf)
            s_a = s if s_a is None else jnp.minimum(s_a, s)
        crossed = jnp.isfinite(s_a)
        near = near | crossed
        inv2 = inv2 + jnp.where(crossed, 1.0 / jnp.maximum(s_a, 1e-30) ** 2, 0.0)
    d0 = jnp.where(a_v == 0.0, 0.0, 1.0 / jnp.sqrt(jnp.maximum(inv2, 1e-30)))
    # where the field is smooth, |φ| / |∇φ| (central differences) is closer; the smaller
    # of the two keeps the bound of one cell
    g = jnp.stack(jnp.gradient(v, *[h[a] for a in range(3)]), axis=-1)
    d0 = jnp.minimum(d0, a_v / jnp.maximum(jnp.linalg.norm(g, axis=-1), 1e-30))
    big = jnp.asarray(jnp.sum(h * (jnp.asarray(v.shape, v.dtype) - 1.0)), v.dtype)
    u0 = jnp.where(near, d0, big)

    def sweep(_, u):
        pad = jnp.pad(u, 1, mode="constant", constant_values=big)
        nb = []
        for a in range(3):
            lo = pad[tuple(slice(0, -2) if b == a else slice(1, -1) for b in range(3))]
            hi = pad[tuple(slice(2, None) if b == a else slice(1, -1) for b in range(3))]
            nb.append(jnp.minimum(lo, hi))
        return jnp.where(near, u, jnp.minimum(u, _godunov(jnp.stack(nb, -1), h)))

    u = jax.lax.fori_loop(0, iterations, sweep, u0)
    return sign * u


def _sl(axis, start, stop):
    return tuple(slice(start, stop) if b == axis else slice(None) for b in range(3))


def _godunov(a, h):
    """Solution u of Σ_k ((u − a_k)⁺ / h_k)² = 1 for neighbour values a [..., 3] and
    spacings h [3]: the largest number of axes m whose a_k lie below the m-axis root
    (axes taken by increasing a_k, sorted by a three-comparator network)."""
    w = [jnp.broadcast_to(1.0 / (h[k] * h[k]), a.shape[:-1]) for k in range(3)]
    a = [a[..., k] for k in range(3)]

    def swap(i, j):
        s = a[j] < a[i]
        a[i], a[j] = jnp.where(s, a[j], a[i]), jnp.where(s, a[i], a[j])
        w[i], w[j] = jnp.where(s, w[j], w[i]), jnp.where(s, w[i], w[j])

    swap(0, 1), swap(1, 2), swap(0, 1)
    u = a[0] + 1.0 / jnp.sqrt(w[0])
    sw = swa = swaa = 0.0
    for m in range(3):
        sw, swa, swaa = sw + w[m], swa + w[m] * a[m], swaa + w[m] * a[m] * a[m]
        if m == 0:
            continue
        disc = swa * swa - sw * (swaa - 1.0)
        root = (swa + jnp.sqrt(jnp.maximum(disc, 0.0))) / sw
        u = jnp.where((u > a[m]) & (disc >= 0.0), root, u)
    return u


def eikonal_loss(grid, band=None):
    """mean over cells of (|∇φ| − 1)², ∇φ the trilinear gradient at each cell's centre
    (the mean of its four edge slopes per axis); 0 for a sampled plane. With `band`,
    only cells whose mean |φ| is below it count (the surface's neighbourhood)."""
    v, h = grid.values, grid.spacing().astype(grid.values.dtype)
    g = []
    for a in range(3):
        s = jnp.diff(v, axis=a) / h[a]
        for b in range(3):
            if b != a:
                s = 0.5 * (jax.lax.slice_in_dim(s, 0, s.shape[b] - 1, axis=b)
                           + jax.lax.slice_in_dim(s, 1, s.shape[b], axis=b))
        g.append(s)
    norm = jnp.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2 + 1e-20)
    r = (norm - 1.0) ** 2
    if band is None:
        return jnp.mean(r)
    centre = v
    for a in range(3):
        centre = 0.5 * (jax.lax.slice_in_dim(centre, 0, centre.shape[a] - 1, axis=a)
                        + jax.lax.slice_in_dim(centre, 1, centre.shape[a], axis=a))
    w = (jnp.abs(jax.lax.stop_gradient(centre)) < band).astype(v.dtype)
    return jnp.sum(w * r) / jnp.maximum(jnp.sum(w), 1.0)
