"""Several views of one scene: cameras stacked along a leading view axis, rendered in one
compiled program.

A batch of V cameras is one camera object of one type and one resolution whose float
leaves carry a leading axis of length V (`eye` [V, 3], `fov` [V], ...): `stack_cameras`
builds it from a list, `orbit` places V cameras around a target. `render_views(scene,
cameras, settings)` maps `jaxrt.render` over that axis with `jax.vmap` (one program,
the views batched like the pixels, not a Python loop) and returns an `Image` whose
arrays have a leading view axis ([V, H, W, 3], ...). Differentiable with respect to
the scene and the cameras, like `render`.

    cameras = jr.views.orbit(8, target=(0, 0.5, 0), distance=5.0, elevation=25.0,
                             width=48, height=48)
    images = jr.render_views(scene, cameras, settings)        # images.rgb: [8, 48, 48, 3]
    loss = jr.fit.l2_loss(images.rgb, targets)

Several devices: `devices=D` (or a list of devices) cuts the view axis into D equal
blocks (V must be a multiple of D) on a one-axis mesh ("views") and renders each block on
its own device with `jax.shard_map`, the scene replicated: the devices never talk while
rendering, and the gradient of a loss summed over views is reduced by JAX (the transpose
of the replication is a sum over devices). `shard_map` rather than a sharding constraint:
XLA cannot partition a Pallas kernel (a custom call), it would run every view on every
device.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec as P

from . import xla
from .camera import PerspectiveCamera, _Camera
from .render import derivative_by_replay, differentiable, render
from .settings import RenderSettings

__all__ = ["stack_cameras", "orbit", "render_views", "num_views", "view"]

#: Name of the mesh axis that the views are sharded over.
AXIS = "views"


def stack_cameras(cameras):
    """One camera whose float leaves have a leading view axis, from a sequence of
    cameras of one type and one resolution (as `jax.tree.map(jnp.stack, ...)`)."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("`stack_cameras(cameras)` needs at least one camera")
    first = cameras[0]
    for i, c in enumerate(cameras):
        if not isinstance(c, _Camera):
            raise TypeError(f"`stack_cameras`: cameras[{i}] is a {type(c).__name__}, expected a jaxrt camera")
        if type(c) is not type(first) or (c.width, c.height) != (first.width, first.height):
            raise ValueError(
                f"`stack_cameras`: cameras[{i}] is a {type(c).__name__} of {c.width}x{c.height}, "
                f"cameras[0] a {type(first).__name__} of {first.width}x{first.height}; views "
                "rendered together need one camera type and one resolution")
    return jax.tree.map(lambda *x: jnp.stack(x), *cameras)


def num_views(cameras):
    """V, the length of the view axis of stacked `cameras`."""
    return int(jnp.shape(cameras.eye)[0]) if jnp.ndim(cameras.eye) == 2 else 1


def view(cameras, i):
    """Camera `i` of stacked `cameras` (a camera like those that were stacked)."""
    return jax.tree.map(lambda x: x[i], cameras)


def orbit(n, target=(0.0, 0.0, 0.0), distance=5.0, elevation=20.0, azimuth=0.0, fov=40.0,
          width=64, height=64, up=(0.0, 1.0, 0.0), turns=1.0):
    """`n` perspective cameras on a circle around `target`, stacked (`stack_cameras`).

    Camera k looks at `target` from distance `distance`, at azimuth
    φk = azimuth + 360° · turns · k / n about the y axis (φ = 0: on the −z side, the
    usual front view) and elevation θk above the xz plane; eye = target + distance ·
    (cos θ sin φ, sin θ, −cos θ cos φ). `elevation` (degrees) is one number or one per
    camera (alternating elevations see tops and undersides from one ring).
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"`orbit(n=...)` must be an integer ≥ 1, got {n!r}")
    elevation = np.broadcast_to(np.asarray(elevation, float), (n,))
    if not np.all(np.abs(elevation) < 90.0):
        raise ValueError(f"`orbit(elevation=...)` must be in (-90, 90) degrees, got {elevation.tolist()}")
    if not float(distance) > 0.0:
        raise ValueError(f"`orbit(distance=...)` must be > 0, got {distance}")
    phi = np.deg2rad(azimuth + 360.0 * turns * np.arange(n) / n)
    theta = np.deg2rad(elevation)
    offsets = float(distance) * np.stack(
        [np.cos(theta) * np.sin(phi), np.sin(theta), -np.cos(theta) * np.cos(phi)], axis=-1)
    t = np.asarray(target, float)
    return stack_cameras([PerspectiveCamera(eye=t + o, target=t, up=up, fov=fov, width=width,
                                            height=height) for o in offsets])


def render_views(scene, cameras, settings=None, *, devices=None):
    """Render `scene` through every camera of stacked `cameras` (`stack_cameras`,
    `orbit`); returns an `Image` whose arrays have a leading view axis [V, ...].

    One compiled program (`jax.vmap` of `jaxrt.render` over the view axis), compiled
    once per scene structure, settings and number of views, with the XLA options of
    `settings.kernel.xla` (`jaxrt.xla`). `devices` (None: one
    device; an integer D, 0 for all local devices; or a list of devices) shards the
    view axis over a one-axis mesh (V a multiple of their number).
    """
    settings = RenderSettings() if settings is None else settings
    if jnp.ndim(cameras.eye) != 2:
        raise ValueError("`render_views(cameras=...)` needs cameras stacked along a view axis "
                         "(eye [V, 3]); use jaxrt.views.stack_cameras or jaxrt.views.orbit")
    mesh = None if devices is None else _view_mesh(devices, num_views(cameras))
    if xla.tracing() and derivative_by_replay(settings, (scene, cameras)):
        return differentiable(_render_views, (scene, cameras), settings, mesh)
    return xla.jitted(_render_views, settings)(scene, cameras, settings, mesh)


def _view_mesh(devices, n):
    if isinstance(devices, (int, np.integer)):
        local = jax.local_devices()
        if devices > len(local):
            raise ValueError(f"`render_views(devices={devices})`: only {len(local)} local devices")
        devices = local if devices == 0 else local[:devices]
    devices = list(devices)
    if n % len(devices):
        raise ValueError(f"`render_views`: {n} views cannot be split evenly over {len(devices)} "
                         "devices (use a multiple of the device count)")
    return Mesh(np.asarray(devices), (AXIS,))


@eqx.filter_jit
def _render_views(scene, cameras, settings, mesh):
    dyn, static = eqx.partition((scene, cameras), eqx.is_array)

    def block(dyn_):
        scene_, cameras_ = eqx.combine(dyn_, static)
        return jax.vmap(lambda camera: render(scene_, camera, settings))(cameras_)

    if mesh is None:
        return block(dyn)
    scene_dyn, camera_dyn = dyn
    specs = (jax.tree.map(lambda _: P(), scene_dyn), jax.tree.map(lambda _: P(AXIS), camera_dyn))
    out_specs = jax.tree.map(lambda _: P(AXIS), jax.eval_shape(block, dyn))
    return jax.shard_map(block, mesh=mesh, in_specs=(specs,), out_specs=out_specs,
                         check_vma=False)(dyn)
