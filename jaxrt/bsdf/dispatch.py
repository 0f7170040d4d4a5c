"""Material dispatch by kind: one evaluation per kind of material in a scene.

A surface hit carries a material index m (traced, per ray). Evaluating every material
of the scene and selecting the one at m (a chain of `where`s) puts a copy of every
material's code into the program, at every site that shades. Instead the materials are
grouped by kind (`jaxrt.kinds`: same class and static structure, e.g. every
`CookTorrance` with a `GGX` distribution, a `SchlickFresnel` and a Lambertian base);
the parameters of a group are stacked, the hit's member is taken by its position in
the group, and the group's code runs once on it:

    f(m) = f_g(θ_{g, j(m)})      g = group of m, j(m) = position of m in g,

then the kinds' results are selected by g. Two GGX Cook–Torrance materials cost one
evaluation, sixteen cost one too; the program grows with the kinds, not the count.
The value is the same as evaluating material m itself (the same operations on the same
numbers), and gradients reach the leaves of material m alone.
"""

import jax
import numpy as np

from ..kinds import group_by_kind, lookup, stack, take


def _select(values, index):
    out = values[0]
    for k in range(1, len(values)):
        out = jax.numpy.where(index == k, values[k], out)
    return out


def dispatch(materials, index, fn, default=None, predicate=None):
    """fn(materials[index]), evaluating fn once per kind of material.

    Args:
      materials: the scene's materials (a sequence).
      index: the material index (traced int32, in range).
      fn: material -> pytree of arrays (the same structure for every material).
      default: the value for materials without `predicate` (required if some lack it).
      predicate: a static test of a material (a flag such as `has_diffuse`, the same
        for every material of a kind); fn is evaluated only for the kinds that pass it.

    Returns fn's pytree for the material at `index`, or `default`.
    """
    groups = [(ix, members) for ix, members in group_by_kind(list(materials))
              if predicate is None or predicate(members[0])]
    if not groups:
        return default
    values = []
    for ix, members in groups:
        if len(members) == 1:
            m = members[0]
        else:
            position = np.zeros(len(materials), np.int32)
            position[list(ix)] = np.arange(len(ix))
            m = take(stack(members), lookup(position, index))
        values.append(fn(m))
    slot = np.full(len(materials), len(groups), np.int32)
    for g, (ix, _) in enumerate(groups):
        slot[list(ix)] = g
    if np.all(slot < len(groups)):  # every material passes: no default needed
        slot_values = values
    elif default is None:
        raise ValueError("dispatch: some materials fail the predicate and no default is given")
    else:
        slot_values = values + [default]
    if len(slot_values) == 1:
        return slot_values[0]
    which = lookup(slot, index)
    return jax.tree_util.tree_map(lambda *xs: _select(list(xs), which), *slot_values)
