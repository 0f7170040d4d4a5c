"""Many children of one kind in one program: stacked evaluation for `Union`.

A union written as a loop, min(f_1(p), …, f_n(p)), puts one copy of every child's
program into the traced program, so its size (and XLA's compile time, which grows
faster than the program) grows with n. Children with the same *structure* (node types
and static fields such as material indices: `jax.tree_util.tree_structure`) differ only
in their leaves, so they can be evaluated as one child whose leaves have a leading axis
of length n:

    d_j = f(p; θ_j) for j = 1..n     (one child program, scanned over the leaves θ_j)
    j*  = argmin_j d_j               (the first minimum: the loop's strict `<`)
    f_∪(p) = d_{j*},  material = m_{j*}.

The program holds one copy of f per kind of child (one `stack` equation per leaf
gathers the children's leaves), so its size does not grow with n. The reduction is a
`lax.scan` with the loop's select, not `vmap` + argmin: on a CPU the scan renders
faster than the loop for many children (64 spheres, 32×32: 16 vs 38 ms,
experiments/bench/scaling.py), where vmap + argmin was slower than the loop (110 vs
26 ms in one interleaved run: it evaluates every child into an [rays, n] array and
gathers from it). The result and its gradient are those of the loop: a chain of
selects, so the gradient flows to child j* alone (through the stack, to that child's
own leaves), as through the loop's select-based min. Exact ties between children of
different groups go to the first child in the list; a tie between a stacked child and
a looped one can still be broken by an ulp of rounding (the two are compiled apart).
The "fused" backend keeps the scan a loop over lanes (`lanes.control._scan_rolled`),
Pallas a loop that loads each child's leaves (`lanes.control._scan_loaded`). A GPU's
replay evaluates the children at once instead, `vmap` + argmin (`march.tape.wide_unions`,
`KernelOptions.replay_wide_unions`): there every iteration of a scan is kernels of its own.

Material indices are data within a group: each primitive's static `material` becomes
an int32 leaf (`material_as_data`), so spheres of sixteen materials are one group of
sixteen, not sixteen groups of one.

`render` stacks the groups once, at the top of its program (`prestack`: a
`StackedUnion`), so that what it does per leaf of the scene outside the SDF (casts,
`stop_gradient` at every march, the replay's per-sample copies, the lane kernels'
parameters) is done per group, not per child."""

import equinox as eqx
import jax
import jax.numpy as jnp

from ..vecmath import safe_norm, select

from .base import SDF, Primitive

# Groups with at least this many members are stacked; smaller ones stay a loop (the
# default of `Union(stack_threshold=...)`, a static field of each union; a constant
# that nothing changes at run time).
# From experiments/bench/scaling.py --only primitives (CPU, 32×32, spheres in two
# groups): groups of 2 and 4 compile slower stacked than looped (6.1 vs 4.0 s, 7.1 vs
# 5.2 s) and render slower (6.1 vs 1.8 ms, 3.8 vs 1.9 ms); groups of 8 compile faster
# stacked (7.3 vs 8.3 s), and from 16 on the loop's compile time runs away.
STACK_THRESHOLD = 8


class _Tagged(SDF):
    """A primitive whose material index is a leaf (int32) rather than a static field,
    so that children that differ only in their materials are one kind of child."""

    child: Primitive
    material: jnp.ndarray

    def eval(self, p):
        return self.child.distance(p), self.material

    def lipschitz(self):
        return self.child.lipschitz()

    def bounding_ball(self):
        return self.child.bounding_ball()


def _untag(prim):
    """A copy of the primitive `prim` with material 0 (static fields cannot be set
    through the pytree)."""
    copy = object.__new__(type(prim))
    copy.__dict__.update(prim.__dict__)
    object.__setattr__(copy, "material", 0)
    return copy


def material_as_data(child):
    """`child` with every primitive's static material index made a leaf (`_Tagged`):
    the same function, whose structure no longer depends on the materials. Primitives
    already tagged (inside a `StackedUnion`) stay as they are."""
    def tag(x):
        if isinstance(x, Primitive):
            return _Tagged(_untag(x), jnp.asarray(x.material, jnp.int32))
        return x

    return jax.tree_util.tree_map(tag, child, is_leaf=lambda x: isinstance(x, (Primitive, _Tagged)))


def group_by_structure(children):
    """[(indices, members)] of `children` grouped by pytree structure, their material
    indices made data (`material_as_data`: children that differ only in their
    materials are one group), in the order of their first member (static: structures
    only). The members are the tagged children."""
    groups = {}
    for i, child in enumerate(children):
        tagged = material_as_data(child)
        groups.setdefault(jax.tree_util.tree_structure(tagged), []).append((i, tagged))
    return [(tuple(i for i, _ in g), [c for _, c in g]) for g in groups.values()]


def stack_nodes(members):
    """One node of the members' common structure whose leaves have a leading axis n."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *members)


def stacked_eval(stacked, p, ids=None, d_before=None, balls=None):
    """(d_{j*}, m_{j*}, ids[j*]) over the n stacked children (ids: their indices in the
    union, default 0..n−1): a `lax.scan` over the children with the loop's select,
    (d, m, i) ← (d_k, m_k, ids[k]) where k = 0 or d_k < d, so the program holds one copy
    of the child (see the module docstring). With `d_before` (the union's distance
    before the group), a child that cannot come nearer than min(d_before, d) is
    skipped (`culled_eval`; `balls`: the members' balls stacked, or None)."""
    from ..march import tape

    n = jax.tree_util.tree_leaves(stacked)[0].shape[0]
    ids = jnp.arange(n, dtype=jnp.int32) if ids is None else jnp.asarray(ids, jnp.int32)
    if tape.widens_unions() and (d_before is None or not tape.culls()):
        # every child at once, the first nearest taken: the scan's result (its select
        # takes a child only when strictly nearer) and gradient (child j* alone); no
        # child is culled here (`culled_eval` evaluates them all outside a long march)
        ds, ms = jax.vmap(lambda child: child.eval(p))(stacked)
        k = jnp.argmin(ds)
        return ds[k], ms[k], ids[k]
    first = jax.tree_util.tree_map(lambda x: x[0], stacked)
    d0, m0 = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype),
                                    jax.eval_shape(first.eval, p))

    def step(carry, xs):
        d, m, j = carry
        child, k, i, ball = xs
        if d_before is None:
            dc, mc = child.eval(p)
        else:
            dc, mc = culled_eval(child, p, jnp.where(k == 0, d_before, jnp.minimum(d, d_before)),
                                 ball)
        take = (k == 0) | (dc < d)
        return (select(take, dc, d), select(take, mc, m), select(take, i, j)), None

    (d, m, j), _ = jax.lax.scan(step, (d0, m0, jnp.int32(0)),
                                (stacked, jnp.arange(n, dtype=jnp.int32), ids, balls))
    return d, m, j


def stacked_lipschitz(stacked):
    """max_j L_j over the stacked children."""
    return jnp.max(jax.vmap(lambda c: jnp.asarray(c.lipschitz()))(stacked))


def union_parts(children, threshold=None, keep=None):
    """The parts of a union of `children`: (parts, ids, stacked), where a part is the
    `stack_nodes` of a group of ≥ `threshold` children of one structure (None:
    `STACK_THRESHOLD`; `stacked` True, `ids` the group's child indices) or one child (the
    others, and those for which `keep(child)` is true; `ids` (i,)), in the order of
    `group_by_structure`. None if no group is stacked."""
    threshold = STACK_THRESHOLD if threshold is None else threshold
    parts, ids, stacked = [], [], []
    for ix, members in group_by_structure(children):
        if len(ix) >= threshold and not (keep is not None and keep(children[ix[0]])):
            parts.append(stack_nodes(members))
            ids.append(ix)
            stacked.append(True)
        else:
            parts += [children[i] for i in ix]
            ids += [(i,) for i in ix]
            stacked += [False] * len(ix)
    if not any(stacked):
        return None
    return tuple(parts), tuple(ids), tuple(stacked)


def parts_eval(parts, ids, stacked, p, balls=None):
    """`union_eval` of the `union_parts` (parts, ids, stacked): candidates of different
    parts are combined by (distance, child index), so that ties go to the first child, as
    in the loop. `balls`: the parts' balls computed ahead (`prestack`), or None."""
    best = None
    balls = (None,) * len(parts) if balls is None else balls
    for part, ix, st, ball in zip(parts, ids, stacked, balls):
        if st:
            dc, mc, ic = stacked_eval(part, p, ix, None if best is None else best[0], ball)
        else:
            dc, mc = part.eval(p) if best is None else culled_eval(part, p, best[0], ball)
            ic = jnp.int32(ix[0])
        if best is None:
            best = (dc, mc, ic)
            continue
        d, m, i = best
        take = (dc < d) | ((dc == d) & (ic < i))
        best = (select(take, dc, d), select(take, mc, m), select(take, ic, i))
    return best[0], best[1]


def parts_lipschitz(parts, stacked):
    """max_i L_i over the `union_parts`."""
    values = [stacked_lipschitz(part) if st else jnp.asarray(part.lipschitz())
              for part, st in zip(parts, stacked)]
    return jnp.max(jnp.stack(values))


#: A union skips only children of at least this many equations (`culled_eval`): a
#: sphere's distance (6) costs no more than the test.
CULL_MIN_EQUATIONS = 12

#: Relative margin of the skip test, so that rounding never skips a child that is an
#: ulp nearer than its bound says: a child is skipped only where its bound exceeds the
#: distance so far by 1e-5 of |p − centre| + radius.
CULL_MARGIN = 1e-5

_EQUATIONS = {}


def enclosing_ball(balls):
    """A `bounding_ball` of the union of shapes with these balls (None if any is None):
    centred at the mean centre, the smallest weight (min_i w_i (|p − c_i| − r_i) ≥
    w (|p − C| − R) outside the big ball)."""
    if not balls or any(b is None for b in balls):
        return None
    centre = sum(b[0] for b in balls) / len(balls)
    radius = jnp.max(jnp.stack([safe_norm(b[0] - centre) + b[1] for b in balls]))
    weight = jnp.min(jnp.stack([jnp.asarray(b[2]) for b in balls]))
    return centre, radius, weight


def _equations(jaxpr):
    n = len(jaxpr.eqns)
    for eqn in jaxpr.eqns:
        for v in eqn.params.values():
            for sub in v if isinstance(v, (list, tuple)) else [v]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    n += _equations(inner)
    return n


def _traced(child, p):
    """(equations of `child.eval`, the shape and dtype of its material), traced once per
    structure (p may be a `jax.ShapeDtypeStruct`)."""
    key = (jax.tree_util.tree_structure(child), tuple(p.shape), p.dtype)
    if key not in _EQUATIONS:
        closed = jax.make_jaxpr(lambda c, x: c.eval(x))(child, p)
        _EQUATIONS[key] = (_equations(closed.jaxpr), closed.out_avals[1])
    return _EQUATIONS[key]


def _costly(child, p):
    """Whether `child.eval` is worth skipping: at least CULL_MIN_EQUATIONS equations."""
    return _traced(child, p)[0] >= CULL_MIN_EQUATIONS


def culled_eval(child, p, d, ball=None):
    """`child.eval(p)`, or where the child's `bounding_ball` shows that it cannot come
    nearer than d (the union's distance so far) at any point of p: (its bound, material
    0), which a union's `dc < d` then never takes. The same union either way (exact,
    ties included: a skipped child has f ≥ bound > d).

    Only in the loops of long marches traced for the "fused" lanes (`march.tape.culls`), where a
    `cond` with a per-ray predicate skips its branch for a tile of rays none of which
    needs it (`lanes.control._cond_skipping`): the rays of a tile march through the
    same region, so a tile evaluates only the children near it. Elsewhere (vmap, the
    Pallas kernel) a cond evaluates both branches, so nothing is skipped.

    `ball`: the child's ball computed ahead (`prestack(balls=True)`: once per render,
    not at every site), else it is computed here."""
    from ..march import tape

    if not tape.culls() or not _costly(child, p):
        return child.eval(p)
    ball = child.bounding_ball() if ball is None else ball
    if ball is None:
        return child.eval(p)
    # the bound decides, and is never the union's value: no derivative through it
    centre, radius, weight = jax.lax.stop_gradient(ball)
    gap = safe_norm(jax.lax.stop_gradient(p) - centre.astype(p.dtype))
    bound = (weight * (gap - radius) - CULL_MARGIN * (gap + radius)).astype(d.dtype)
    need = jnp.any(~((bound > 0.0) & (bound > jax.lax.stop_gradient(d))))
    m_shape = _traced(child, p)[1]

    def near():
        # the material passes the cond as a float (exact for indices < 2²⁴): an integer
        # output of a cond gets a float0 tangent under JVP, built by a primitive that
        # the lane kernels do not run
        dc, mc = child.eval(p)
        return dc, mc.astype(d.dtype)

    far = (jnp.broadcast_to(bound, jnp.shape(d)), jnp.zeros(m_shape.shape, d.dtype))
    dc, mc = jax.lax.cond(need, near, lambda: far)
    return dc, mc.astype(m_shape.dtype)


def union_eval(children, p, threshold=None, balls=None):
    """(min_i f_i(p), material of the first minimising child), as the loop
    `d = where(d_i < d, d_i, d)` over i = 1..n, with groups of ≥ `threshold` children
    of one structure evaluated stacked (None: `STACK_THRESHOLD`; `parts_eval`).
    `balls`: the children's balls computed ahead (`prestack`), or None."""
    split = union_parts(children, threshold)
    balls = (None,) * len(children) if balls is None else balls
    if split is None:
        d, m = children[0].eval(p)
        for child, ball in zip(children[1:], balls[1:]):
            dc, mc = culled_eval(child, p, d, ball)
            take = dc < d
            m = select(take, mc, m)
            d = select(take, dc, d)
        return d, m
    return parts_eval(*split, p)


def union_lipschitz(children, threshold=None):
    """max_i L_i, with the same grouping as `union_eval`."""
    split = union_parts(children, threshold)
    if split is None:
        return jnp.max(jnp.stack([jnp.asarray(c.lipschitz()) for c in children]))
    return parts_lipschitz(split[0], split[2])


class StackedUnion(SDF):
    """A `Union` whose groups are stacked once, ahead of the program (`prestack`): the
    same function (`parts_eval`, the same operations as `Union.eval`), whose pytree holds
    one [n, ...] leaf per leaf of a group's structure instead of n leaves. What a render
    does per leaf of the scene (casts, `stop_gradient` at every march, the replay's
    per-sample copies and their sums, the lane kernels' parameter unpacking) is then
    done per group, whatever n. Gradients reach each child's own leaves through the stack.

    `parts`: stacked groups and single children (`union_parts`); planes are never
    stacked (`integrator.analytic_planes` meets them analytically)."""

    parts: tuple
    ids: tuple = eqx.field(static=True)
    stacked: tuple = eqx.field(static=True)
    materials: frozenset = eqx.field(static=True)
    balls: tuple | None = None
    stack_threshold: int = eqx.field(static=True, default=STACK_THRESHOLD)  # the `Union`'s

    def eval(self, p):
        return parts_eval(self.parts, self.ids, self.stacked, p, self.balls)

    def lipschitz(self):
        return parts_lipschitz(self.parts, self.stacked)

    def children(self):
        """The parts that are single children."""
        return tuple(c for c, st in zip(self.parts, self.stacked) if not st)

    def material_ids(self):
        return set(self.materials)


def _balls(parts, stacked):
    """The `bounding_ball` of each part that `culled_eval` would skip (stacked parts:
    their members' balls stacked), else None."""
    out = []
    for part, st in zip(parts, stacked):
        first = jax.tree_util.tree_map(lambda x: x[0], part) if st else part
        leaves = [x for x in jax.tree_util.tree_leaves(first) if jnp.issubdtype(x.dtype, jnp.floating)]
        p = jax.ShapeDtypeStruct((3,), leaves[0].dtype if leaves else jnp.float32)
        ball = first.bounding_ball() if _costly(first, p) else None
        if ball is not None and st:
            ball = jax.vmap(lambda c: c.bounding_ball())(part)
        out.append(ball)
    return tuple(out)


def prestack(surface, balls=False):
    """`surface` with every `Union` that stacks a group (`union_parts`) replaced by its
    `StackedUnion` (the same function). `render` calls it at the top of its program.
    With `balls`, each union also holds its children's bounding balls (`_balls`), which
    `culled_eval` then reads instead of computing them at every site. Rotations get
    their matrices here too (`domain.with_matrices`). Unions stacked ahead (`stacked`)
    get their matrices and balls alone."""
    from .domain import with_matrices

    return _stack_unions(with_matrices(surface), balls)


def stacked(surface):
    """`surface` with every `Union` that has a group of at least `stack_threshold`
    children of one structure replaced by its `StackedUnion`: the same function, which
    renders the same image, and whose pytree holds one [n, ...] leaf per leaf of a
    group's structure (the n spheres' centres: one [n, 3] leaf) instead of n leaves.

    For fits of many primitives: differentiate with respect to the stacked surface
    (`eqx.tree_at(lambda s: s.surface, scene, stacked(scene.surface))`). The gradient
    is then a few stacked leaves, whose program does not grow with n, where a gradient
    of n separate leaves hands each its own slice of the stacked cotangent (each a
    kernel of XLA's). `value_and_grad` of 8 and 256 spheres + a plane (16×12, 2 CPU
    cores, jax 0.10.2; lowering + compiling, `experiments/bench/compile.py --stacked`):
    "jax" 4.3 / 4.5 s against 4.3 / 7.5 s, "fused" 7.5 / 7.5 s against 8.1 / 11.0 s.
    `unstacked` gives the unions back."""
    return _stack_unions(surface, balls=False)


def _stack_unions(surface, balls):
    """`prestack` without the matrices (`stacked` with `balls` False)."""
    from .combine import Union
    from .primitives import Plane

    def convert(node):
        if type(node) is StackedUnion:  # stacked ahead: its single parts, and its balls
            parts = tuple(p if st else _stack_unions(p, balls)
                          for p, st in zip(node.parts, node.stacked))
            new = eqx.tree_at(lambda u: u.parts, node, parts)
            if balls and node.balls is None:
                new = eqx.tree_at(lambda u: u.balls, new, _balls(parts, node.stacked),
                                  is_leaf=lambda x: x is None)
            return new
        if type(node) is not Union:
            return node
        children = tuple(_stack_unions(c, balls) for c in node.children_)
        split = union_parts(children, node.stack_threshold, keep=lambda c: isinstance(c, Plane))
        if split is None:
            new = eqx.tree_at(lambda u: u.children_, node, children)
            if balls:
                new = new.with_balls(_balls(children, (False,) * len(children)))
            return new
        return StackedUnion(*split, frozenset(node.material_ids()),
                            _balls(split[0], split[2]) if balls else None, node.stack_threshold)

    return jax.tree_util.tree_map(convert, surface,
                                  is_leaf=lambda x: type(x) in (Union, StackedUnion))


def unstacked(surface):
    """The inverse of `stacked`: every `StackedUnion` a `Union` of its children in their
    order, each primitive's material index static again (read from the group's int32
    leaf: call it on concrete values, outside `jit`)."""
    from .combine import Union

    def convert(node):
        if type(node) is not StackedUnion:
            return node
        children = {}
        for part, ix, st in zip(node.parts, node.ids, node.stacked):
            members = [jax.tree_util.tree_map(lambda x, k=k: x[k], part) for k in range(len(ix))] if st else [part]
            children.update(zip(ix, (_retagged(m) for m in members)))
        return Union(*(unstacked(children[i]) for i in range(len(children))),
                     stack_threshold=node.stack_threshold)

    return jax.tree_util.tree_map(convert, surface, is_leaf=lambda x: type(x) is StackedUnion)


def _retagged(child):
    """`child` with each `_Tagged` primitive its primitive again, its material static."""
    def untag(x):
        if not isinstance(x, _Tagged):
            return x
        copy = _untag(x.child)
        object.__setattr__(copy, "material", int(x.material))
        return copy

    return jax.tree_util.tree_map(untag, child, is_leaf=lambda x: isinstance(x, _Tagged))
