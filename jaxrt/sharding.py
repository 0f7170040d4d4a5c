"""Rendering on several devices: the image's rows sharded with `jax.sharding`.

`RenderSettings(devices=D)` makes `render` split the image's rows over the local
devices with `jax.shard_map` over a one-axis `Mesh` ("pixels"): each device traces its
rows with the whole scene (replicated, a few kilobytes), and the bands of rows are the
shards of the output arrays. By default each device gets one contiguous band, and rays
being independent the devices never talk to each other; with `BAND_ROWS` > 0 narrower
bands are dealt to the devices in turn and dealt back with one `all_to_all`
(`shard_rows`). Either way the image is the same as on one device (the same program on
the same rays). `devices=0` uses every local device.

Several hosts: call `jax.distributed.initialize()` on every host first (see JAX's
"multi-process" guide); `jax.devices()` then lists the devices of all hosts and
`shard_rows(fn, replicated, samples, rows, devices=jax.devices())` shards over all of
them, each process holding its own band of the result (a global `jax.Array`).

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


#: Rows per band when bands are dealt to the devices in turn (`shard_rows`); 0 gives
#: each device one contiguous band.
BAND_ROWS = 0


def shard_rows(fn, replicated, samples, rows, devices, band_rows=None):
    """`fn(replicated, samples_band, band_rows) -> dict of [band, ...]` on every device.

    `samples` [N, 2] are row-major over `rows` rows. The rows are cut into bands of
    `band_rows` (default `BAND_ROWS`) dealt to the D devices in turn (band k to device
    k mod D), so that every device gets rows from the whole image and the work is
    balanced even where parts of the image march longer than others (the sky, a
    horizon). One `all_to_all` then deals the rendered bands back: device j ends with
    the j-th contiguous block of rows ((D − 1)/D of the image crosses devices once).
    The rows are padded (edge rows, cropped afterwards) to a multiple of
    band_rows · D². `band_rows=0`: one contiguous band per device, no exchange.
    Returns the dict of [N, ...] arrays in image order, sharded along the first axis.
    """
    d = len(devices)
    n = samples.shape[0]
    per_row = n // rows
    b = BAND_ROWS if band_rows is None else band_rows
    if b == 0 or d == 1:  # one contiguous band per device
        b, bands = math.ceil(rows / d), 1
    else:  # bands per device: a multiple of d, for the all_to_all
        b = min(b, math.ceil(rows / d**2))
        bands = math.ceil(rows / (b * d**2)) * d
    total = b * d * bands
    pad = total - rows
    if pad:
        samples = jnp.concatenate([samples, jnp.repeat(samples[-per_row:], pad, axis=0)])
    chunk = b * per_row  # samples per band

    def deal(x):  # image order -> device order: band k to device k mod d
        x = x.reshape((bands, d, chunk) + x.shape[1:])
        return jnp.swapaxes(x, 0, 1).reshape((total * per_row,) + x.shape[3:])

    mesh = pixel_mesh(devices)
    samples = jax.lax.with_sharding_constraint(deal(samples), NamedSharding(mesh, P(AXIS)))

    def undeal(x):
        """This device's bands (k = m·d + i for local m) -> its block of image rows."""
        if bands == 1:
            return x
        x = x.reshape((d, bands // d, chunk) + x.shape[1:])
        x = jax.lax.all_to_all(x, AXIS, 0, 0)  # [source device i, m, ...]
        return jnp.swapaxes(x, 0, 1).reshape((bands * chunk,) + x.shape[3:])

    def body(rep, s):
        return jax.tree_util.tree_map(undeal, fn(rep, s, total // d))

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
