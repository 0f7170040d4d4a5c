"""Cameras and eye rays (notes, "Eye ray and camera").

A camera has an orthonormal frame (u right, v up, w forward) built from eye, target
and up. Image coordinates (x, y) ∈ [−1, 1] run left→right and bottom→top; pixel
(row 0, column 0) is the top-left one and pixel centres sit at half-integers.

- Perspective: r = normalize(x·aspect·tan(fov/2)·u + y·tan(fov/2)·v + w), P(t) = e + t r.
- Orthographic: o = e + x·aspect·size·u + y·size·v, P(t) = o + t w.

Each ray also carries its pixel cone: footprint radius r(t) = r0 + spread · t, used for
the pixel-relative hit epsilon and for silhouette coverage.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .sdf.base import as_float
from .vecmath import cross, normalize


class _Camera(eqx.Module):
    eye: jnp.ndarray
    target: jnp.ndarray
    up: jnp.ndarray
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def frame(self):
        """(u, v, w): right, up and forward unit vectors."""
        w = normalize(self.target - self.eye)
        u = normalize(cross(w, self.up))
        v = cross(u, w)
        return u, v, w

    def screen(self, px, py):
        """Continuous pixel coordinates (px right, py down, in pixels) to x, y ∈ [−1, 1]."""
        x = 2.0 * px / self.width - 1.0
        y = 1.0 - 2.0 * py / self.height
        return x, y

    @property
    def aspect(self):
        return self.width / self.height

    def with_resolution(self, width, height):
        """The same camera with another image size (validated like the constructor)."""
        # width/height are static fields, which `eqx.tree_at` cannot replace: rebuild.
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        fields.update(width=width, height=height)
        return type(self)(**fields)


def _check_frame(name, eye, target, up, width, height):
    for label, n in (("width", width), ("height", height)):
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"`{name}({label}=...)` must be an integer ≥ 1, got {n!r}")
    if any(isinstance(a, jax.core.Tracer) for a in (eye, target, up)):
        return
    e, t, u = (np.asarray(a, dtype=float) for a in (eye, target, up))
    if np.linalg.norm(t - e) == 0.0:
        raise ValueError(f"`{name}`: eye and target must differ, both are {e.tolist()}")
    if np.linalg.norm(np.cross(t - e, u)) < 1e-9 * np.linalg.norm(t - e) * max(np.linalg.norm(u), 1e-300):
        raise ValueError(f"`{name}(up=...)` must not be parallel to the viewing direction")


class PerspectiveCamera(_Camera):
    """Pinhole camera with a vertical field of view `fov` in degrees, in (0, 180).

    Differentiable: `eye`, `target`, `up`, `fov`.
    """

    fov: jnp.ndarray

    def __init__(self, eye=(0.0, 0.0, -5.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                 fov=40.0, width=320, height=240):
        self.eye = as_float(eye, (3,), "PerspectiveCamera(eye=...)")
        self.target = as_float(target, (3,), "PerspectiveCamera(target=...)")
        self.up = as_float(up, (3,), "PerspectiveCamera(up=...)")
        self.fov = as_float(fov, (), "PerspectiveCamera(fov=...)")
        _check_frame("PerspectiveCamera", self.eye, self.target, self.up, width, height)
        if not isinstance(self.fov, jax.core.Tracer) and not (0.0 < float(self.fov) < 180.0):
            raise ValueError(f"`PerspectiveCamera(fov=...)` must be in (0, 180) degrees, got {fov}")
        self.width, self.height = int(width), int(height)

    def generate_ray(self, px, py):
        """(origin, direction, cone) of the ray through continuous pixel position (px, py).

        `cone` = (r0, spread): pixel-cone radius r(t) = r0 + spread · t along the ray.
        """
        u, v, w = self.frame()
        x, y = self.screen(px, py)
        tan_half = jnp.tan(jnp.deg2rad(self.fov) * 0.5)
        d = x * self.aspect * tan_half * u + y * tan_half * v + w
        direction = normalize(d)
        spread = tan_half / self.height  # half a pixel at unit distance along w
        return self.eye, direction, jnp.stack([jnp.zeros_like(spread), spread])


class OrthographicCamera(_Camera):
    """Parallel projection; `size` is half the height of the view in world units.

    Differentiable: `eye`, `target`, `up`, `size`.
    """

    size: jnp.ndarray

    def __init__(self, eye=(0.0, 0.0, -5.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                 size=1.0, width=320, height=240):
        self.eye = as_float(eye, (3,), "OrthographicCamera(eye=...)")
        self.target = as_float(target, (3,), "OrthographicCamera(target=...)")
        self.up = as_float(up, (3,), "OrthographicCamera(up=...)")
        self.size = as_float(size, (), "OrthographicCamera(size=...)")
        _check_frame("OrthographicCamera", self.eye, self.target, self.up, width, height)
        if not isinstance(self.size, jax.core.Tracer) and not float(self.size) > 0.0:
            raise ValueError(f"`OrthographicCamera(size=...)` must be > 0, got {size}")
        self.width, self.height = int(width), int(height)

    def generate_ray(self, px, py):
        """(origin, direction, cone) of the ray through continuous pixel position (px, py)."""
        u, v, w = self.frame()
        x, y = self.screen(px, py)
        origin = self.eye + x * self.aspect * self.size * u + y * self.size * v
        r0 = self.size / self.height
        return origin, w, jnp.stack([r0, jnp.zeros_like(r0)])


def pixel_samples(camera, spp, seed):
    """Continuous sample positions [H·W·spp, 2] (px, py), pixel-major, row-major pixels.

    spp = 1 gives pixel centres. spp > 1 gives N-rooks (Latin hypercube) stratified
    samples: sample k of a pixel lies in x-stratum k and in the y-stratum of a random
    permutation, with a jitter inside its stratum; the pattern is drawn from a fixed
    seed and differs per pixel.
    """
    h, w = camera.height, camera.width
    rows, cols = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
    base = jnp.stack([cols.ravel(), rows.ravel()], axis=-1).astype(float)  # [HW, 2]
    if spp == 1:
        return base + 0.5
    key = jax.random.PRNGKey(seed)
    kx, ky, kp = jax.random.split(key, 3)
    n = h * w
    jitter = jax.random.uniform(kx, (n, spp, 2))
    strata_x = jnp.arange(spp)[None, :]
    strata_y = jax.vmap(lambda k: jax.random.permutation(k, spp))(jax.random.split(kp, n))
    offs = (jnp.stack([jnp.broadcast_to(strata_x, (n, spp)), strata_y], axis=-1) + jitter) / spp
    return (base[:, None, :] + offs).reshape(n * spp, 2)
