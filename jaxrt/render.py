"""render(): the one place that maps the per-ray kernels over the pixels of an image."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .camera import pixel_samples
from .integrator import trace_radiance
from .settings import RenderSettings


class Image(eqx.Module):
    """A rendered image: linear HDR `rgb` [H, W, 3] and AOVs.

    depth     [H, W] distance along the ray to the first hit (max_distance on a miss).
    normal    [H, W, 3] world-space unit normal facing the camera (0 on a miss).
    albedo    [H, W, 3] base colour of the material hit (0 on a miss).
    steps     [H, W] sphere-tracing steps of the primary ray.
    coverage  [H, W] fraction of the pixel's samples that hit a surface.
    Values are averaged over the pixel's samples (box filter).
    """

    rgb: jnp.ndarray
    depth: jnp.ndarray
    normal: jnp.ndarray
    albedo: jnp.ndarray
    steps: jnp.ndarray
    coverage: jnp.ndarray


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
    origins, directions, cones = jax.vmap(camera.generate_ray)(samples[:, 0], samples[:, 1])

    def kernel(ray):
        o, d, cone = ray
        return trace_radiance(scene, o, d, cone, settings)

    n = samples.shape[0]
    if settings.batch_size is None or settings.batch_size >= n:
        out = jax.vmap(kernel)((origins, directions, cones))
    else:
        out = jax.lax.map(kernel, (origins, directions, cones), batch_size=settings.batch_size)
    h, w, spp = camera.height, camera.width, settings.spp
    out = {k: v.reshape((h, w, spp) + v.shape[1:]).mean(axis=2) for k, v in out.items()}
    return Image(**out)


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
