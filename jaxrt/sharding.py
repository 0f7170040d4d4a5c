"""Rendering on several devices: the image's rows sharded with `jax.sharding`.

`RenderSettings(devices=D)` makes `render` split the image into D bands of rows, one
per local device, with `jax.shard_map` over a one-axis `Mesh` ("pixels"): each device
traces its band with the whole scene (replicated, a few kilobytes) and the bands are
the shards of the output arrays. Rays are independent, so the devices never talk to
each other; the image is the same as on one device (the same program on the same
rays). `devices=0` uses every local device.

Several hosts: call `jax.distributed.initialize()` on every host first (see JAX's
"multi-process" guide); `jax.devices()` then lists the devices of all hosts and
`sharded_map(fn, args, devices=jax.devices())` shards over all of them, each process
holding its own band of the result (a global `jax.Array`).

Fitting with several views: shard the *views* instead, `jax.shard_map` over a mesh
whose axis splits the batch of cameras, with the scene replicated and the loss summed
with `jax.lax.psum`; see `shard_views`.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

__all__ = ["local_devices", "pixel_mesh", "shard_rows", "shard_views", "rows_sharded"]

AXIS = "pixels"


def local_devices(count):
    """The first `count` local devices (0: all of them), with a clear error."""
    devices = jax.local_devices()
    if count == 0:
        return devices
    if count > len(devices):
        raise ValueError(
            f"RenderSettings.devices = {count}, but only {len(devices)} local devices "
            f"exist ({jax.default_backend()}); on a CPU, XLA_FLAGS="
            f"--xla_force_host_platform_device_count={count} makes more (set it before "
            "importing jax)"
        )
    return devices[:count]


def pixel_mesh(devices):
    """A one-axis mesh named "pixels" over `devices`."""
    return Mesh(np.asarray(devices), (AXIS,))


def shard_rows(fn, replicated, samples, rows, devices):
    """`fn(replicated, samples_band, band_rows) -> dict of [band, ...]` on every device.

    `samples` [N, 2] are row-major over `rows` rows; the rows are padded to a multiple
    of the device count (edge rows, cropped afterwards) and split into equal bands.
    Returns the dict of [N, ...] arrays, sharded along the first axis.
    """
    d = len(devices)
    n = samples.shape[0]
    per_row = n // rows
    band = math.ceil(rows / d)
    pad = band * d - rows
    if pad:
        samples = jnp.concatenate([samples, jnp.repeat(samples[-per_row:], pad, axis=0)])
    mesh = pixel_mesh(devices)
    samples = jax.lax.with_sharding_constraint(samples, NamedSharding(mesh, P(AXIS)))

    def body(rep, s):
        return fn(rep, s, band)

    out = jax.shard_map(body, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS),
                        check_vma=False)(replicated, samples)
    if pad:
        out = jax.tree_util.tree_map(lambda x: x[:n], out)
    return out


def rows_sharded(tree, devices):
    """Constrain every array of `tree` to be sharded along its first axis (image rows),
    so that the rendered image stays distributed instead of being gathered."""
    sharding = NamedSharding(pixel_mesh(devices), P(AXIS))
    return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, sharding), tree)


def shard_views(loss_fn, params, views, devices=None):
    """Σ over views of `loss_fn(params, view)`, the views sharded over `devices`.

    `views` is a pytree whose leaves have a leading axis of views (its length a
    multiple of the device count); `params` is replicated. Differentiable: the
    gradient of the sum is the sum of per-device gradients (`psum`).
    """
    devices = jax.local_devices() if devices is None else devices
    mesh = pixel_mesh(devices)

    def body(p, v):
        per_view = jax.vmap(lambda one: loss_fn(p, one))(v)
        return jax.lax.psum(jnp.sum(per_view), AXIS)

    return jax.shard_map(body, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(),
                         check_vma=False)(params, views)
