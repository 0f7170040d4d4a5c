"""render(): the one place that maps the per-ray kernels over the pixels of an image."""

import equinox as eqx
import jax
import jax.numpy as jnp

from . import sharding, silhouette
from .camera import pixel_samples
from .integrator import trace_radiance
from .kernels.fused import resolve_backend
from .settings import RenderSettings


class Image(eqx.Module):
    """A rendered image: linear HDR `rgb` [H, W, 3] and AOVs.

    depth     [H, W] distance along the ray to the first hit (max_distance on a miss).
    normal    [H, W, 3] world-space unit normal facing the camera (0 on a miss).
    albedo    [H, W, 3] base colour of the material hit (0 on a miss).
    steps     [H, W] sphere-tracing steps of the primary ray.
    coverage  [H, W] fraction of the pixel's samples that hit a surface.
    Values are averaged over the pixel's samples (box filter). AOVs left out of
    `RenderSettings.aovs` are None.
    """

    rgb: jnp.ndarray
    depth: jnp.ndarray | None = None
    normal: jnp.ndarray | None = None
    albedo: jnp.ndarray | None = None
    steps: jnp.ndarray | None = None
    coverage: jnp.ndarray | None = None


def render(scene, camera, settings=None):
    """Render `scene` through `camera`; returns an `Image`.

    Compiled once per scene *structure* and settings: changing parameter values (any
    float in the scene or camera) reuses the compiled program.
    """
    settings = RenderSettings() if settings is None else settings
    dtype = _dtype(settings)
    scene, camera = _cast((scene, camera), dtype)
    return _render(scene, camera, settings)


@eqx.filter_jit
def _render(scene, camera, settings):
    samples = pixel_samples(camera, settings.spp, settings.seed).astype(camera.eye.dtype)
    h, w, spp = camera.height, camera.width, settings.spp

    def kernel(ray, scene=scene, camera=camera):
        o, d, cone, xy = ray
        out = trace_radiance(scene, o, d, cone, settings)
        if settings.silhouette:
            out = silhouette.blend(scene, camera, xy, out, settings)
        return {k: out[k] for k in ("rgb",) + settings.aovs}

    def trace_block(params, samples, grid, offset):
        """Every sample of a block of the image (all of it, or one device's block):
        `grid` (rows, columns of samples), `offset` its first (row, column)."""
        scene, camera = params
        if resolve_backend(settings.backend) != "jax":
            return _fused(scene, camera, samples, settings, kernel, grid, offset)
        origins, directions, cones = jax.vmap(camera.generate_ray)(samples[:, 0], samples[:, 1])
        rays = (origins, directions, cones, samples)
        n = samples.shape[0]
        if settings.batch_size is None or settings.batch_size >= n:
            return jax.vmap(lambda r: kernel(r, scene, camera))(rays)
        return jax.lax.map(lambda r: kernel(r, scene, camera), rays,
                           batch_size=settings.batch_size)

    if settings.devices == 1:
        out = trace_block((scene, camera), samples, (h, w * spp), (0, 0))
        out = {k: v.reshape((h, w * spp) + v.shape[1:]) for k, v in out.items()}
    else:  # a block of the image on each device, and the image kept in blocks on them
        devices = sharding.local_devices(settings.devices)
        out = sharding.shard_image(trace_block, (scene, camera), samples, (h, w * spp), devices)
    out = {k: v.reshape((h, w, spp) + v.shape[2:]).mean(axis=2) for k, v in out.items()}
    if settings.devices != 1:
        out = sharding.image_sharded(out, devices)
    return Image(**out)


def _fused(scene, camera, samples, settings, kernel, grid, offset):
    """The per-sample kernel run lane-wise by `jaxrt.kernels` (backend "fused"/"pallas"/
    "auto") on a block `grid` of samples at `offset` in the image; gradients through the
    vmapped path above."""
    from .kernels.fused import map_samples

    def one(params, px, py):
        return kernel((*params[1].generate_ray(px, py), jnp.stack([px, py])), *params)

    def reference(params, s):
        rays = (*jax.vmap(params[1].generate_ray)(s[:, 0], s[:, 1]), s)
        return jax.lax.map(lambda r: kernel(r, *params), rays,
                           batch_size=min(settings.batch_size or s.shape[0], s.shape[0]))

    # pixel_samples gives pixel centres at spp 1: the Pallas kernel then computes them
    return map_samples(one, (scene, camera), samples, settings, reference, grid=grid,
                       centres=offset if settings.spp == 1 else None)


def _dtype(settings):
    if settings.dtype == "float64":
        if not jax.config.jax_enable_x64:
            raise ValueError(
                'RenderSettings.dtype = "float64" needs 64-bit JAX: call '
                'jax.config.update("jax_enable_x64", True) before creating the scene'
            )
        return jnp.float64
    return jnp.float32


def _cast(tree, dtype):
    def cast(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) and x.dtype != dtype:
            return x.astype(dtype)
        return x

    return jax.tree_util.tree_map(cast, tree)


def compile_render(scene, camera, settings=None):
    """Compile ahead of time; returns `f(scene, camera) -> Image` for scenes of this
    structure (used to report compile and render time apart)."""
    settings = RenderSettings() if settings is None else settings
    dtype = _dtype(settings)
    compiled = _render.lower(*_cast((scene, camera), dtype), settings).compile()
    return lambda scene, camera: compiled(*_cast((scene, camera), dtype), settings)
