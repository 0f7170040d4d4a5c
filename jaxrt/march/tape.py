"""The tape: what the marches of a render write, so that a loop-free program can replay them.

A render's per-sample program (`integrator.trace_radiance`, `silhouette.blend`) calls
marches: bounded loops with no gradient (sphere tracing, soft shadows, height fields,
the silhouette searches). Each march is called through `march(fn, *args)`, and the tape
decides what that call does:

- no tape (`off`, the default): `fn(*args)` runs, as in any JAX program;
- `recording()`: `fn(*args)` runs and its result (no gradient) is appended to the tape,
  in the static order of the program;
- `replaying(entries)`: nothing runs; the next entry of the tape is returned.

So the same Python program, run once recording (in the fast lane-wise kernels, with
no gradient) and once replaying (plain vmapped `jnp` over the image, no loop left),
computes the same values, and the replay is differentiable: everything outside the
marches (Newton steps at the recorded roots, normals, shading, penumbrae at their
recorded minima) carries gradients (`jaxrt.render`). A replay vmapped over a block of
rays can skip what the record skipped for dead rays (`gathering`: the secondary rays
of the ray tree).

Marches inside `jax.vmap`, `lax.scan` or `lax.cond` write tracers of that
transformation, which must leave it through its outputs: the program calls
`tape.vmap(fn)`, `tape.scan` and `tape.cond` instead, which run `fn` under a sub-tape
and return (recording) or take (replaying) its entries as batched outputs/inputs. The entries of a tape are a list of pytrees of
arrays, one per march (a sub-tape is one entry: the list of its entries, batched).
"""

import contextlib
import threading

import jax
import jax.numpy as jnp

_STATE = threading.local()


def _transpose_stop_gradient():
    """Give JAX's `stop_gradient` the transpose of the identity, unless it has a rule
    already (lineax, which optimistix imports, registers this one too).

    A replay's `_gathered` skips its dead batches with a `lax.cond` inside the render's
    custom JVP rule. Under a `vmap` over views (`views.render_views`, or a user's) the
    cond's predicate is batched, and JAX's batching rule turns the cond into selects
    whose operands, tangents included, it wraps in `stop_gradient`, a primitive with
    no transpose: the reverse pass of a multi-view render of any scene with a mirror or
    glass failed ("Transpose rule ... for 'stop_gradient' not implemented"; JAX issues
    #22011 and #39219). There `stop_gradient` stands on the operands of the branch that
    the outputs' select drops, whose cotangent is zero, so the identity is its
    transpose. Elsewhere a `stop_gradient` never reaches a linear program (its JVP has
    a zero tangent)."""
    try:
        from jax._src.ad_util import stop_gradient_p
        from jax._src.interpreters import ad
    except ImportError:  # another JAX: leave it be
        return
    ad.primitive_transposes.setdefault(stop_gradient_p, lambda ct, x: (ct,))


_transpose_stop_gradient()


class Tape:
    """The entries of one trace of the per-sample program (`mode` "record" or "replay")."""

    def __init__(self, mode, entries=None):
        self.mode = mode
        self.entries = [] if entries is None else list(entries)
        self.position = 0

    def take(self):
        if self.position >= len(self.entries):
            raise RuntimeError("jaxrt.march.tape: the replayed program reads more marches "
                               "than were recorded (the program differs from the record)")
        entry = self.entries[self.position]
        self.position += 1
        return entry

    def check_consumed(self):
        if self.mode == "replay" and self.position != len(self.entries):
            raise RuntimeError(f"jaxrt.march.tape: {len(self.entries)} marches recorded, "
                               f"{self.position} replayed (the program differs from the record)")


def current():
    """The active `Tape`, or None."""
    return getattr(_STATE, "tape", None)


@contextlib.contextmanager
def _using(tape):
    previous = current()
    _STATE.tape = tape
    try:
        yield tape
    finally:
        _STATE.tape = previous


def recording():
    """Context: marches run and append their results to a fresh tape (yielded)."""
    return _using(Tape("record"))


@contextlib.contextmanager
def replaying(entries):
    """Context: marches return the `entries` of a recording, in order; all must be read."""
    with _using(Tape("replay", entries)) as tape:
        yield tape
    tape.check_consumed()


def off():
    """Context: marches run and nothing is recorded (abstract evaluations, nested marches)."""
    return _using(None)


def march(fn, *args, keep=None):
    """`fn(*args)` (a march: a pytree of arrays, no gradient) through the active tape.

    `keep`: for a march that returns a dict, the keys that the tape holds; the others
    are by-products for the program that runs the march (a replay, which gets only the
    kept ones, computes them otherwise)."""
    tape = current()
    if tape is not None and tape.mode == "replay":
        return tape.take()
    with off():  # marches called by a march are part of it
        out = jax.tree_util.tree_map(jax.lax.stop_gradient, fn(*args))
    if tape is not None:
        tape.entries.append(out if keep is None else {k: out[k] for k in keep})
    return out


def vmap(fn, gather=None):
    """`jax.vmap(fn)` (over axis 0 of every argument) whose marches are on the tape, as one
    entry of batched sub-entries. `gather`: (live, dead), with `live(*a)` a predicate of
    one element and `dead(*a)` equal to `fn(*a)` (in every value the program reads) where
    it is false, marching nothing; a replay under `gathering` then runs `fn` only for the
    elements where `live` holds, in batches (`_gathered`), with `fn` under the same
    promise as `cond`'s `gather`."""

    def batched(*args):
        tape = current()
        if tape is None:
            return jax.vmap(fn)(*args)
        gathered = getattr(_STATE, "gather", None)
        if tape.mode == "replay" and gather is not None and gathered is not None:
            live, dead = gather
            return _gathered(jax.vmap(live)(*args), fn, dead, args, tape.take(), *gathered)
        if tape.mode == "record":
            def inner(*a):
                with recording() as sub:
                    out = fn(*a)
                return out, sub.entries

            out, entries = jax.vmap(inner)(*args)
            tape.entries.append(entries)
            return out

        def inner(entries, *a):
            with replaying(entries):
                return fn(*a)

        return jax.vmap(inner)(tape.take(), *args)

    return batched


def scan(step, init, xs):
    """`lax.scan(step, init, xs)` whose marches are on the tape (one entry, stacked over
    the iterations)."""
    tape = current()
    if tape is None:
        return jax.lax.scan(step, init, xs)
    if tape.mode == "record":
        def inner(carry, x):
            with recording() as sub:
                carry, y = step(carry, x)
            return carry, (y, sub.entries)

        carry, (ys, entries) = jax.lax.scan(inner, init, xs)
        tape.entries.append(entries)
        return carry, ys

    def inner(carry, x_entries):
        x, entries = x_entries
        with replaying(entries):
            return step(carry, x)

    return jax.lax.scan(inner, init, (xs, tape.take()))


@contextlib.contextmanager
def _setting(name, value):
    previous = getattr(_STATE, name, None)
    setattr(_STATE, name, value)
    try:
        yield
    finally:
        setattr(_STATE, name, previous)


def lanes(backend):
    """Context: the program is traced for the lane kernels of `backend` ("fused" or
    "pallas"). On "fused", `cond` lets a block of rays skip work that none of its rays
    needs."""
    return _setting("lanes", backend)


def lane_backend():
    """The lane backend the program is traced for (`lanes`), or None."""
    return getattr(_STATE, "lanes", None)


def forward_gradients(on=True):
    """Context: the program's gradients of the SDF are taken in forward mode
    (`trace.value_and_gradient`): traced for a Pallas kernel whose scans stay loops
    (`KernelOptions.pallas_scan_loops`)."""
    return _setting("forward_gradients", on)


def forward_gradient():
    """Whether gradients of the SDF are taken in forward mode (`forward_gradients`)."""
    return bool(getattr(_STATE, "forward_gradients", False))


def wide_unions(on=True):
    """Context: a stacked union evaluates all its children at once and takes the
    nearest (`sdf.stack.stacked_eval`), instead of a scan over them: for a GPU's replay,
    where every iteration of a scan is kernels of their own
    (`KernelOptions.replay_wide_unions`)."""
    return _setting("wide_unions", on)


def widens_unions():
    """Whether stacked unions are evaluated wide (`wide_unions`)."""
    return bool(getattr(_STATE, "wide_unions", False))


def skips_blocks():
    """Whether `cond` skips per block of rays: traced for "fused" (`lanes`)."""
    return lane_backend() == "fused"


def stepping():
    """Context: the loop of a long march (sphere tracing, a soft shadow) is traced. Its
    SDF evaluations are the ones where, on "fused", a union skips the children that no
    ray of a tile can reach (`culls`; `sdf.stack.culled_eval`): tens to hundreds per
    ray. The few others (normals, Newton and settling steps) evaluate every child, which
    keeps their `cond`s out of the program."""
    return _setting("stepping", True)


def culls():
    """Whether a union skips far children here: a long march's loop (`stepping`) traced
    for "fused" (`lanes`)."""
    return skips_blocks() and bool(getattr(_STATE, "stepping", False))


def gathering(axis_name, rays):
    """Context: the program is replayed under `jax.vmap(..., axis_name=axis_name)` over
    a block of rays, and a `cond` or `vmap` that allows it (`gather`) evaluates its
    function only for the rays (elements) of the block where its predicate holds
    (`_gathered`), in batches of `rays`. The function must close over nothing that
    varies between the block's rays (the replay passes the scene unbatched), or every
    batch would be computed for every ray (the same values, at the cost of a vmap over
    the block)."""
    return _setting("gather", (axis_name, rays))


def cond(pred, fn, dead, *operands, gather=False):
    """`fn(*operands)`, whose marches are one entry on the tape; `dead(*operands)` must
    equal it (in every value the program reads) where `pred` is false, and march nothing.

    Traced for the "fused" kernels (`lanes`), this is `lax.cond(pred, fn, dead)`: a
    block of rays in which no ray has `pred` skips `fn` (the lanes' rule), and the entry
    holds zeros for the rays that skipped it. Elsewhere (under `vmap`, where a cond would
    run both branches) `fn` runs for every ray, so the replay of a record calls `fn`
    with zero entries where `pred` is false: it must stay finite there. With `gather`
    (the caller's promise that `fn` closes over nothing that varies between rays but
    what `gathering` allows), a replay under `gathering` runs `fn` only for the rays
    where `pred` holds, in batches (`_gathered`)."""
    tape = current()
    if tape is not None and tape.mode == "replay":
        entries = tape.take()
        gathered = getattr(_STATE, "gather", None)
        if gather and gathered is not None:
            one = lambda x: x[None]  # noqa: E731
            out = _gathered(pred[None], fn, dead, jax.tree_util.tree_map(one, operands),
                            jax.tree_util.tree_map(one, entries), *gathered)
            return jax.tree_util.tree_map(lambda x: x[0], out)

        with replaying(entries):
            return fn(*operands)
    if not skips_blocks():
        if tape is None:
            return fn(*operands)
        with recording() as sub:
            out = fn(*operands)
        tape.entries.append(sub.entries)
        return out
    if tape is None:
        return jax.lax.cond(pred, fn, dead, *operands)

    def live(*a):
        with recording() as sub:
            out = fn(*a)
        return out, sub.entries

    shapes = jax.eval_shape(live, *operands)[1]

    def skipped(*a):
        return dead(*a), jax.tree_util.tree_map(lambda s: jax.numpy.zeros(s.shape, s.dtype), shapes)

    out, entries = jax.lax.cond(pred, live, skipped, *operands)
    tape.entries.append(entries)
    return out


def _gathered(pred, fn, dead, operands, entries, axis, rays):
    """The replay of `fn` over the m elements of one ray of a block vmapped over `axis`
    (pred [m], operands and entries [m, ...]: a `cond`, m = 1, or a `vmap` of a ray's
    children), which computes `fn` only for the elements of the block where `pred` holds.

    The block's predicates, operands and entries are gathered (`all_gather`: one array
    over the block, not a per-ray value) and flattened to its n·m elements, those where
    `pred` holds are sorted first (a stable sort keeps their order), and `lax.map` runs
    `fn` (vmapped, with the entries replayed) over batches of `rays` of them; a batch
    past the last such element takes `dead` instead (a `lax.cond` on one scalar: a
    branch, not a select). Each ray then reads its own m results back. The gradient goes
    back the same way: the batches' cotangents are scattered onto the block's rays (the
    transpose of `all_gather` and of the gathers). `fn` runs under `jax.checkpoint`, so
    the reverse pass keeps a batch's inputs instead of its intermediates (zeros for
    every skipped batch, else).

    The ray tree (`integrator._trace_tree`, `_trace_tree_scan`) shades its secondary rays
    through this: few rays of an image are alive in a slot of the tree (those that met
    a mirror or glass)."""
    live, operands, entries = jax.lax.all_gather((pred, operands, entries), axis)
    n, m = live.shape
    live, operands, entries = jax.tree_util.tree_map(
        lambda x: x.reshape((n * m,) + x.shape[2:]), (live, operands, entries))
    total = n * m
    rays = min(rays, total)
    batches = -(-total // rays)
    order = jnp.argsort(~live, stable=True)  # the elements where pred holds first
    order = jnp.pad(order, (0, batches * rays - total)).reshape(batches, rays)
    count = jnp.sum(live)

    @jax.checkpoint
    def run(block):
        def one(a, e):
            with replaying(e), _setting("gather", None):
                return fn(*a)

        return jax.vmap(one)(*block)

    def skip(block):
        return jax.vmap(lambda a: dead(*a))(block[0])

    def batch(k_rows):
        k, rows = k_rows
        block = jax.tree_util.tree_map(lambda x: x[rows], (operands, entries))
        return jax.lax.cond(k * rays < count, run, skip, block)

    out = jax.lax.map(batch, (jnp.arange(batches), order))
    index = jnp.arange(total, dtype=order.dtype)
    position = jnp.zeros(total, order.dtype).at[order.reshape(-1)[:total]].set(index)
    mine = position.reshape(n, m)[jax.lax.axis_index(axis)]
    return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:])[mine], out)
