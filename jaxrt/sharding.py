"""Rendering on several devices: the image sharded with `jax.sharding`.

`RenderSettings(devices=D)` makes `render` cut the image into D contiguous blocks of
columns (or of rows, `RenderSettings.split`) and trace each on its own local device with
`jax.shard_map` over a one-axis `Mesh` ("pixels"): each device gets the whole scene
(replicated, a few kilobytes) and the offset of its block, its rays are independent of
the others', so the devices never talk to each other, and the blocks are the shards of
the output arrays (a global `jax.Array` split along that axis). The image is the same
as on one device (the same program on the same rays). `devices=0` uses every local
device.

Columns by default: in the usual framing the top of an image (sky, far ground, a
horizon) marches longer than the bottom, while left and right are alike. On the Warp
scene the step-count model (`experiments/bench/warp_steps.py`) puts 57% of the march
work in the top half and 52% in the left half.

Several hosts: call `jax.distributed.initialize()` on every host first (see JAX's
"multi-process" guide); `jax.devices()` then lists the devices of all hosts and
`shard_image(fn, replicated, samples, grid, devices=jax.devices())` shards over all of
them, each process holding its own block of the result (a global `jax.Array`).

Fitting with several views: shard the *views* instead, `jax.shard_map` over a mesh
whose axis splits the batch of cameras, with the scene replicated and the loss summed
with `jax.lax.psum`; see `shard_views`.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

__all__ = ["local_devices", "pixel_mesh", "shard_image", "shard_views", "image_sharded"]

AXIS = "pixels"

#: The image axis cut into one block per device unless a call says otherwise
#: (`render` passes `RenderSettings.split`): "columns" or "rows". A constant: nothing
#: changes it at run time.
SPLIT = "columns"


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


def _spec(split):
    if split not in ("rows", "columns"):
        raise ValueError(f'split = {split!r}: expected "rows" or "columns"')
    return P(AXIS) if split == "rows" else P(None, AXIS)


def shard_image(fn, replicated, samples, grid, devices, split=None):
    """`fn(replicated, block_samples, block_grid, offset) -> dict of [n, ...]` on every
    device, for its block of the image.

    `samples` [rows · cols, 2] are row-major over `grid` = (rows, cols). The axis
    `split` (default `SPLIT`) is cut into len(devices) equal blocks (padded with copies
    of the last row or column, cropped afterwards); device k gets block k: its samples
    [n, 2] (row-major over block_grid), block_grid and the block's (row, column) offset
    in the grid (traced integers). Returns the dict of [rows, cols, ...] arrays, sharded
    along the split axis.
    """
    split = SPLIT if split is None else split
    spec = _spec(split)
    axis = 0 if split == "rows" else 1
    d = len(devices)
    size = grid[axis]
    per = -(-size // d)
    s = samples.reshape(tuple(grid) + samples.shape[1:])
    if per * d != size:
        pad = [(0, 0)] * s.ndim
        pad[axis] = (0, per * d - size)
        s = jnp.pad(s, pad, mode="edge")

    def body(rep, block):
        r, c = block.shape[:2]
        start = jax.lax.axis_index(AXIS) * per
        zero = jnp.zeros_like(start)
        offset = (start, zero) if axis == 0 else (zero, start)
        out = fn(rep, block.reshape((r * c,) + block.shape[2:]), (r, c), offset)
        return {k: v.reshape((r, c) + v.shape[1:]) for k, v in out.items()}

    out = jax.shard_map(body, mesh=pixel_mesh(devices), in_specs=(P(), spec), out_specs=spec,
                        check_vma=False)(replicated, s)
    if per * d != size:
        out = {k: jax.lax.slice_in_dim(v, 0, size, axis=axis) for k, v in out.items()}
    return out


def image_sharded(tree, devices, split=None):
    """Constrain every array of `tree` ([rows, cols, ...]) to be sharded along the split
    axis, so that the rendered image stays distributed instead of being gathered."""
    sharding = NamedSharding(pixel_mesh(devices), _spec(SPLIT if split is None else split))
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
