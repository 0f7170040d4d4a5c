"""Things of one kind as data: group by structure, stack, look up by a traced index.

A scene holds many materials, lights and primitives, but few *kinds* of them: a kind
is a structure (`jax.tree_util.tree_structure`: the class, its static fields, which
optional fields are set) and the shapes of its leaves. Instances of one kind differ
only in their leaves, so they are one instance whose leaves have a leading axis n
(`stack`), and a traced index picks one of them (`take`): the program holds one copy
of the kind's code, whatever n (design.md, habit 12).

`take` and `lookup` are a `lax.scan` over the n slots with the where-chain
`out = where(index == k, x_k, out)`: the same value as `x[index]` for an index in
range (slot 0 otherwise), one copy of the select in the program whatever n, and for the
lane backends (`jaxrt.kernels.lanes`, which unroll scans) the chain of selects that
they run best. A gather would be one operation too, but lanes enumerates the index
combinations of a gather with several per-ray indices (a batched level of the ray
tree), which it cannot for more than two.
"""

import jax
import jax.numpy as jnp
import numpy as np


def kind(x):
    """The static key of `x`'s kind: pytree structure and leaf shapes and dtypes."""
    leaves, tree = jax.tree_util.tree_flatten(x)
    return tree, tuple((jnp.shape(v), jnp.result_type(v)) for v in leaves)


def group_by_kind(items):
    """[(indices, members)] of `items` grouped by `kind`, in the order of each group's
    first member (static)."""
    groups = {}
    for i, item in enumerate(items):
        groups.setdefault(kind(item), []).append(i)
    return [(tuple(ix), [items[i] for i in ix]) for ix in groups.values()]


def stack(members):
    """One instance of the members' kind whose leaves have a leading axis n."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *members)


def take(stacked, index):
    """The member `index` (traced int) of a `stack`ed tree: member 0 when out of range.

    A `lax.scan` of the where-chain over the members (see the module docstring)."""
    leaves = jax.tree_util.tree_leaves(stacked)
    if not leaves:
        return stacked
    n = leaves[0].shape[0]
    if n == 1:
        return jax.tree_util.tree_map(lambda x: x[0], stacked)
    index = jnp.asarray(index)

    def step(out, xs):
        member, k = xs
        hit = index == k
        return jax.tree_util.tree_map(lambda a, b: jnp.where(hit, b, a), out, member), None

    first = jax.tree_util.tree_map(lambda x: x[0], stacked)
    rest = jax.tree_util.tree_map(lambda x: x[1:], stacked)
    out, _ = jax.lax.scan(step, first, (rest, jnp.arange(1, n, dtype=index.dtype)))
    return out


def lookup(table, index):
    """table[index] for a static integer or bool table (a sequence) and a traced index
    (entry 0 when out of range); a constant when every entry is the same."""
    table = np.asarray(table)
    table = table.astype(np.int32) if table.dtype.kind in "iu" else table
    if np.all(table == table[0]):
        return jnp.asarray(table[0])
    return take(jnp.asarray(table), index)
