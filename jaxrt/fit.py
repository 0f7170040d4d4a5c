"""Image losses and the fitting driver: scene, material, light and camera parameters
fitted to target images (inverse rendering), and BRDFs to measurements
(`jaxrt.fit_brdf`).

A fit is four choices: which leaves are free (`free_parameters`), how values stay legal
(`transforms`: a radius through softplus, a roughness through the logistic function,
η through 1 + softplus, see `Transform`), how an image is compared with the target
(`l2_loss`, `l1_loss`, or `image_residuals` for least squares), and what moves the
free leaves. `fit` takes either

- an optimistix minimiser (default BFGS): the whole fit is one compiled program, the
  renderer traced once inside the solver's loop; or
- an optax optimiser (`adam` below: Adam with a schedule and per-group learning rates,
  or any `optax.GradientTransformation`): a plain Python loop around one compiled step
  (loss, gradient, update), with a loss history, a callback, a tqdm progress bar, and
  checkpoints every N steps that a later call resumes from after an interruption.

`fit_least_squares` runs Gauss–Newton/Levenberg–Marquardt on residuals (their Jacobian
by forward mode, one pass per free scalar). Every driver returns one `FitResult`.

    params, rebuild = jr.fit.free_parameters(
        scene, lambda s: (s.surface.child.radius, s.surface.offset))
    targets = jr.render_views(true_scene, cameras, settings).rgb          # [V, H, W, 3]
    loss = lambda p, _: jr.fit.l2_loss(jr.render_views(rebuild(p), cameras, settings).rgb,
                                       targets)
    result = jr.fit.fit(loss, params, jr.fit.adam(0.01, steps=300), max_steps=300,
                        transforms=(jr.fit.POSITIVE, None), checkpoint="fit.npz")
    fitted_scene = rebuild(result.params)

Outlines only have gradients with `RenderSettings(silhouette=True)` (`jaxrt.silhouette`);
without it a shape's size and position are observable through its shading alone.
"""

import dataclasses
import os
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx

from . import xla


# --------------------------------------------------------------------------- losses


def l2_loss(image, target, weights=None):
    """Mean squared error mean(w · (image − target)²) over all pixels and channels.

    `weights` (broadcastable to the images, default 1) can mask or emphasise pixels.
    """
    r = image - target
    return _weighted_mean(r * r, weights)


def l1_loss(image, target, weights=None, delta=0.0):
    """Mean absolute error mean(w · ρ(image − target)), robust to outliers.

    ρ(x) = |x| for delta = 0 (its gradient is sign(x): 0 at exactly 0); for delta > 0
    the Charbonnier form sqrt(x² + δ²) − δ, smooth at 0 and |x| − δ far from it.
    """
    r = image - target
    rho = jnp.sqrt(r * r + delta * delta) - delta if delta > 0.0 else jnp.abs(r)
    return _weighted_mean(rho, weights)


def _weighted_mean(values, weights):
    """Σ w · values / Σ w, with w = `weights` broadcast to the values (default 1)."""
    w = jnp.ones_like(values) if weights is None else jnp.broadcast_to(weights, values.shape)
    return jnp.sum(w * values) / jnp.maximum(jnp.sum(w), 1e-30)


def image_residuals(render_image, target, weights=None):
    """A residual function for `fit_least_squares`: params, args ↦ sqrt(w) · (render_image(
    params) − target), flattened. Its sum of squares is l2_loss times Σw."""
    sw = None if weights is None else jnp.sqrt(jnp.broadcast_to(weights, target.shape))

    def residuals(params, args=None):
        r = render_image(params) - target
        return jnp.ravel(r if sw is None else sw * r)

    return residuals


def free_parameters(tree, where):
    """(params, rebuild): the leaves that `where(tree)` selects (any pytree of arrays, as
    for `eqx.tree_at`) and the function that puts new values of them back into `tree`.
    Everything not selected stays fixed."""
    params = where(tree)

    def rebuild(new_params):
        return eqx.tree_at(where, tree, new_params)

    return params, rebuild


def relative_error(fitted, truth):
    """max over leaves of |fitted − truth| / max(|truth|, 1e-12), elementwise."""
    errors = jax.tree_util.tree_map(
        lambda a, b: jnp.max(jnp.abs(a - b) / jnp.maximum(jnp.abs(b), 1e-12)), fitted, truth)
    return jnp.max(jnp.stack(jax.tree_util.tree_leaves(errors)))


# --------------------------------------------------------------------------- transforms


_KINDS = ("identity", "softplus", "exp", "sigmoid")
#: Inverse transforms clip values this far (relative to the range) inside an open range.
INVERSE_MARGIN = 1e-6


@dataclasses.dataclass(frozen=True)
class Transform:
    """A map from an unconstrained value u to a legal one x, so that any optimiser step
    gives a legal value:

      "identity"  x = u
      "softplus"  x = lo + log(1 + eᵘ)            (x > lo; ≈ lo + u for large u)
      "exp"       x = lo + eᵘ                     (x > lo; steps are relative)
      "sigmoid"   x = lo + (hi − lo) / (1 + e⁻ᵘ)  (lo < x < hi)

    `inverse` maps a legal value back (clipped `INVERSE_MARGIN` inside an open range).
    Hashable by value, so fits with equal transforms share their compiled program.
    """

    kind: str = "identity"
    lo: float = 0.0
    hi: float = 1.0

    def __post_init__(self):
        if self.kind not in _KINDS:
            raise ValueError(f"`Transform(kind={self.kind!r})`: expected one of {_KINDS}")
        if self.kind == "sigmoid" and not self.hi > self.lo:
            raise ValueError(f"`Transform(lo={self.lo}, hi={self.hi})`: expected lo < hi")

    def __call__(self, u):
        u = jnp.asarray(u)
        if self.kind == "softplus":
            return self.lo + jax.nn.softplus(u)
        if self.kind == "exp":
            return self.lo + jnp.exp(u)
        if self.kind == "sigmoid":
            return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(u)
        return u

    def inverse(self, x):
        x = jnp.asarray(x, dtype=jnp.result_type(float, x))
        if self.kind == "identity":
            return x
        if self.kind == "sigmoid":
            s = jnp.clip((x - self.lo) / (self.hi - self.lo), INVERSE_MARGIN, 1.0 - INVERSE_MARGIN)
            return jnp.log(s) - jnp.log1p(-s)
        y = jnp.maximum(x - self.lo, INVERSE_MARGIN)
        if self.kind == "exp":
            return jnp.log(y)
        return y + jnp.log(-jnp.expm1(-y))  # softplus⁻¹(y) = log(eʸ − 1)


IDENTITY = Transform("identity")
#: Radii, extents, intensities, albedos: x > 0 through softplus.
POSITIVE = Transform("softplus")
#: x > 0 through exp: steps are relative (scales spanning decades, exponents).
LOG = Transform("exp")
#: Roughness, reflectances, blend fractions: x in (0, 1) through the logistic function.
UNIT = Transform("sigmoid", 0.0, 1.0)
#: Indices of refraction of a dense medium: η > 1 through 1 + softplus.
ABOVE_ONE = Transform("softplus", 1.0)


def above(lo):
    """x > lo through lo + softplus(u)."""
    return Transform("softplus", float(lo))


def between(lo, hi):
    """lo < x < hi through the logistic function."""
    return Transform("sigmoid", float(lo), float(hi))


def _is_transform(x):
    return x is None or isinstance(x, Transform)


def _prefix(tree, params):
    """`tree` with the keys of a dict of parameters that a dict `tree` leaves out as None."""
    if isinstance(tree, dict) and isinstance(params, dict):
        return {k: tree.get(k) for k in params}
    return tree


def constrain(raw, transforms):
    """Unconstrained values → legal ones. `transforms` is a prefix of the parameter
    tree: a `Transform` (or None for identity) applies to every leaf under it (a dict
    may leave out keys of a dict of parameters: identity)."""
    if transforms is None:
        return raw
    return jax.tree.map(lambda t, sub: sub if t is None else jax.tree.map(t, sub),
                        _prefix(transforms, raw), raw, is_leaf=_is_transform)


def unconstrain(params, transforms):
    """Legal values → unconstrained ones (the inverse of `constrain`)."""
    if transforms is None:
        return params
    return jax.tree.map(lambda t, sub: sub if t is None else jax.tree.map(t.inverse, sub),
                        _prefix(transforms, params), params, is_leaf=_is_transform)


# --------------------------------------------------------------------------- optimisers


def scale_by_leaf(scales):
    """An optax transformation multiplying each leaf's update by its scale: `scales` is
    a prefix of the parameter tree (a number applies to every leaf under it, None = 1;
    a dict may leave out keys of a dict of parameters, which then have scale 1).
    After Adam (whose steps are about the learning rate in size whatever the gradient)
    these are per-group learning rates: `optax.chain(optax.adam(lr), scale_by_leaf(s))`
    moves group g by about lr · s_g per step."""

    def update(updates, state, params=None):
        del params
        out = jax.tree.map(lambda s, sub: sub if s is None else jax.tree.map(lambda u: s * u, sub),
                           _prefix(scales, updates), updates, is_leaf=lambda x: x is None)
        return out, state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def schedule(learning_rate, steps=None, *, kind="cosine", warmup=0, end_factor=0.01):
    """A learning-rate schedule (an optax schedule, step ↦ rate): "constant", "cosine"
    (warm up linearly over `warmup` steps, then cosine decay to end_factor · rate at
    `steps`; a warm-up as long as the run or longer is cut to half of it) or
    "exponential" (decay to end_factor · rate at `steps`)."""
    if kind == "constant" or steps is None:
        return optax.constant_schedule(learning_rate)
    if kind == "cosine":
        warmup = int(steps) // 2 if warmup >= int(steps) else warmup
        return optax.warmup_cosine_decay_schedule(
            0.0 if warmup else learning_rate, learning_rate, max(warmup, 1) if warmup else 1,
            max(int(steps), 2), end_value=learning_rate * end_factor)
    if kind == "exponential":
        return optax.exponential_decay(learning_rate, int(steps), end_factor)
    raise ValueError(f"`schedule(kind={kind!r})`: expected 'constant', 'cosine' or 'exponential'")


def adam(learning_rate=1e-2, steps=None, *, kind="cosine", warmup=0, end_factor=0.01, scales=None,
         b1=0.9, b2=0.999):
    """Adam (Kingma & Ba 2015) with a learning-rate `schedule` over `steps` and per-group
    learning rates `scales` (`scale_by_leaf`; a prefix of the parameter tree, in the
    unconstrained space that the optimiser sees)."""
    opt = optax.adam(schedule(learning_rate, steps, kind=kind, warmup=warmup,
                              end_factor=end_factor), b1=b1, b2=b2)
    return opt if scales is None else optax.chain(opt, scale_by_leaf(scales))


def reset_moments(state):
    """An optax state with every Adam moment estimate forgotten: each
    `optax.ScaleByAdamState` back to its initial value (m = v = 0, count 0, so that the
    bias correction 1/(1 − β^t) restarts too); schedules keep their step counts.

    For a fit whose parameters are moved by something other than the optimiser (a grid
    re-distanced, `jaxrt.sdf.redistance`): the moments gathered on the old values would
    steer the next steps on the new ones."""

    def reset(s):
        if isinstance(s, optax.ScaleByAdamState):
            zeros = lambda t: jax.tree.map(jnp.zeros_like, t)  # noqa: E731
            return s._replace(count=jnp.zeros_like(s.count), mu=zeros(s.mu), nu=zeros(s.nu))
        return s

    return jax.tree.map(reset, state, is_leaf=lambda s: isinstance(s, optax.ScaleByAdamState))


# --------------------------------------------------------------------------- results


class FitResult(NamedTuple):
    """The outcome of a fit (every driver of jaxrt returns one).

    params    the fitted values (legal: transforms applied).
    loss      the objective there.
    steps     steps taken.
    result    optimistix solvers: their `optimistix.RESULTS`; optax loops: why the
              loop stopped, "max_steps", "atol" (loss ≤ atol), "callback" or
              "non-finite loss" (params are then the last finite iterate).
    history   losses [steps + 1]: one before each optax step and the final one (the
              optimistix solvers: start and end only).
    solution  the `optimistix.Solution` (None for optax loops).
    info      driver-specific extras (dict), e.g. `jaxrt.fit_brdf`'s material and errors.
    """

    params: Any
    loss: Any
    steps: int
    result: Any
    history: np.ndarray
    solution: Any = None
    info: dict = {}

    @property
    def converged(self):
        """True when an optimistix solver reported success or an optax loop reached its
        `atol` or was stopped by its callback."""
        if isinstance(self.result, str):
            return self.result in ("atol", "callback")
        return bool(self.result == optx.RESULTS.successful)


class FitProgress(NamedTuple):
    """What a callback of an optax fit sees after each step: `step` steps done,
    `loss` before that step, `params` (legal values) after it, and the loss `history`
    so far (numpy, one value per step)."""

    step: int
    loss: float
    params: Any
    history: np.ndarray


# --------------------------------------------------------------------------- drivers


def fit(loss_fn, params, solver=None, *, args=None, max_steps=256, throw=False, transforms=None,
        atol=None, callback=None, progress=None, checkpoint=None, checkpoint_every=50,
        refresh=None):
    """Minimise `loss_fn(params, args)` (a scalar) over `params`; returns a `FitResult`.

    `solver`: an optimistix minimiser (default `optimistix.BFGS(rtol=1e-6, atol=1e-9)`),
    run as one compiled program (`throw=False` returns the last iterate when it stops
    early; `result.result` says why); or an optax `GradientTransformation` (`adam`),
    run for `max_steps` steps of one compiled step function, gradients by reverse mode.

    `transforms`: a prefix of `params` of `Transform`s (None: identity): the solver
    moves u with params = transform(u), so values stay legal.

    Optax loops only:
      atol         stop once the loss is ≤ atol.
      callback     called after every step with a `FitProgress`; returning True stops.
      progress     show a tqdm bar (None: when max_steps ≥ 100).
      checkpoint   a path (.npz): the state (u, optimiser state, step, history) is
                   written there every `checkpoint_every` steps and at the end
                   (atomically), and a fit started with an existing checkpoint resumes
                   from it, reaching the same iterates as an uninterrupted run.
      refresh      `refresh(params) -> args`, called with the legal values before
                   every step (outside the compiled step): the step's loss sees its
                   result as `args`. For values the loss needs at the current iterate
                   but does not differentiate, computed by a program of their own: the
                   forward render of a straight-through estimator (experiments/inverse/
                   common.py), so that it is not traced into the gradient step.
    """
    if isinstance(solver, optax.GradientTransformation):
        return _fit_optax(loss_fn, params, solver, args, max_steps, transforms, atol, callback,
                          progress, checkpoint, checkpoint_every, refresh)
    if checkpoint is not None or callback is not None or refresh is not None:
        raise ValueError("`fit(checkpoint=..., callback=..., refresh=...)` need an optax optimiser "
                         "(an optimistix solver runs as one compiled program)")
    solver = optx.BFGS(rtol=1e-6, atol=1e-9) if solver is None else solver
    raw = unconstrain(params, transforms)
    start = xla.call_collected(_loss, loss_fn, transforms, raw, args)
    solution = xla.call_collected(_minimise, loss_fn, transforms, solver, raw, args, max_steps,
                                  throw)
    value = constrain(solution.value, transforms)
    loss = loss_fn(value, args)
    return FitResult(value, loss, int(solution.stats["num_steps"]), solution.result,
                     np.array([float(start), float(loss)]), solution)


def fit_least_squares(residual_fn, params, solver=None, *, args=None, max_steps=256,
                      throw=False, transforms=None):
    """Minimise ½‖residual_fn(params, args)‖² with an optimistix least-squares solver,
    default `optimistix.LevenbergMarquardt(rtol=1e-6, atol=1e-9)`; `transforms` as for
    `fit`. The loss reported is the mean squared residual."""
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9) if solver is None else solver
    raw = unconstrain(params, transforms)
    solution = xla.call_collected(_least_squares, residual_fn, transforms, solver, raw, args,
                                  max_steps, throw)
    value = constrain(solution.value, transforms)
    r = residual_fn(value, args)
    loss = jnp.mean(r * r)
    return FitResult(value, loss, int(solution.stats["num_steps"]), solution.result,
                     np.array([np.nan, float(loss)]), solution)


@eqx.filter_jit
def _loss(loss_fn, transforms, raw, args):
    return loss_fn(constrain(raw, transforms), args)


@eqx.filter_jit
def _minimise(loss_fn, transforms, solver, raw, args, max_steps, throw):
    fn = lambda u, a: loss_fn(constrain(u, transforms), a)  # noqa: E731
    return optx.minimise(fn, solver, raw, args=args, max_steps=max_steps, throw=throw)


@eqx.filter_jit
def _least_squares(residual_fn, transforms, solver, raw, args, max_steps, throw):
    dtype = jnp.result_type(*jax.tree.leaves(raw))  # lineax's Jacobian wants one dtype throughout
    fn = lambda u, a: jax.tree.map(lambda r: r.astype(dtype), residual_fn(constrain(u, transforms), a))  # noqa: E731
    return optx.least_squares(fn, solver, raw, args=args, max_steps=max_steps, throw=throw)


@eqx.filter_jit
def _optax_step(loss_fn, transforms, optimiser, raw, state, args):
    """One step: (loss at u, u after the update, optimiser state after it)."""
    loss, grad = jax.value_and_grad(lambda u: loss_fn(constrain(u, transforms), args))(raw)
    updates, state = optimiser.update(grad, state, raw)
    return loss, optax.apply_updates(raw, updates), state


def _strong(tree):
    """The tree with weakly typed arrays (from Python numbers) made strongly typed, so
    that the compiled step sees the same types before and after an update (one compile)."""
    return jax.tree.map(lambda x: jnp.array(x, dtype=jnp.result_type(x)) if eqx.is_array(x) else x, tree)


class _Step:
    """The compiled step of one fit: `_optax_step` lowered and compiled once, on the
    first step's arguments, then called as that executable.

    The step's outputs carry the shardings of the programs inside it (a render sharded
    over views, `render_views(devices=...)`, returns NamedShardings of its mesh), not
    those of the first step's inputs (uncommitted arrays on the default device). The jit
    cache keys on input shardings, so feeding the outputs back to `_optax_step` would
    compile it again on step 2; the compiled executable instead takes any inputs whose
    shardings are equivalent to those it was compiled for (the same devices, the same
    layout): step k's outputs are step k+1's inputs as they are, on the device, with no
    copy through the host. Lowering and compiling share JAX's caches with plain calls of
    `_optax_step`: a second fit of the same loss and types compiles nothing. XLA compiles
    it with the options of the renders traced in the loss (their
    `RenderSettings.kernel.xla`; `jaxrt.xla.compile_collected`)."""

    def __init__(self, loss_fn, transforms, optimiser):
        self.statics = (loss_fn, transforms, optimiser)
        self.compiled = None

    def __call__(self, raw, state, args):
        if self.compiled is None:
            self.compiled = xla.compile_collected(_optax_step, *self.statics, raw, state, args)
        return self.compiled(*self.statics, raw, state, args)


def _fit_optax(loss_fn, params, optimiser, args, max_steps, transforms, atol, callback, progress,
               checkpoint, checkpoint_every, refresh=None):
    def step_args(raw):
        return args if refresh is None else refresh(constrain(raw, transforms))

    raw = _strong(unconstrain(params, transforms))
    state = _strong(optimiser.init(raw))
    step, history = 0, []
    if checkpoint is not None and os.path.exists(checkpoint):
        raw, state, step, history = load_checkpoint(checkpoint, (raw, state))
    if progress is None:
        progress = max_steps >= 100
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_steps, initial=step, desc="fit", leave=False, dynamic_ncols=True)
    why, prev = "max_steps", None
    run_step = _Step(loss_fn, transforms, optimiser)
    try:
        while step < max_steps:
            loss, new_raw, new_state = run_step(raw, state, step_args(raw))
            loss = float(loss)
            if not np.isfinite(loss):  # back to the last iterate with a finite loss
                why = "non-finite loss"
                if prev is not None:
                    (raw, state), step = prev, step - 1
                break
            history.append(loss)  # the loss at iterate `step`
            if atol is not None and loss <= atol:
                why = "atol"
                break
            prev = (raw, state)
            raw, state, step = new_raw, new_state, step + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3e}", refresh=False)
            if checkpoint is not None and (step % checkpoint_every == 0 or step == max_steps):
                save_checkpoint(checkpoint, (raw, state), step, history)
            if callback is not None and callback(
                    FitProgress(step, loss, constrain(raw, transforms), np.asarray(history))):
                why = "callback"
                break
    finally:
        if bar is not None:
            bar.close()
    value = constrain(raw, transforms)
    # the final loss from the compiled step (its update discarded): no second program
    loss = run_step(raw, state, step_args(raw))[0]
    history = history[:step] + [float(loss)]
    if checkpoint is not None:
        save_checkpoint(checkpoint, (raw, state), step, history[:step])
    return FitResult(value, loss, step, why, np.asarray(history))


# --------------------------------------------------------------------------- checkpoints


def save_checkpoint(path, tree, step, history):
    """Write the arrays of `tree` (unconstrained params and optimiser state), the step
    and the loss history to `path` (.npz), atomically (`jaxrt.io` writers' rename)."""
    from .io import _atomic_write

    leaves, treedef = jax.tree.flatten(tree)
    arrays = {f"leaf_{i}": np.asarray(x) for i, x in enumerate(leaves)}

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, step=np.asarray(step), history=np.asarray(history, float),
                     treedef=np.asarray(str(treedef)), **arrays)

    _atomic_write(path, write)


def load_checkpoint(path, like):
    """(tree, step, history) from a checkpoint of a tree with the structure, shapes and
    dtypes of `like`; a clear error naming the file when they differ."""
    leaves, treedef = jax.tree.flatten(like)
    with np.load(path) as z:
        if str(z["treedef"]) != str(treedef) or any(f"leaf_{i}" not in z for i in range(len(leaves))):
            raise ValueError(f"{path}: checkpoint of another fit (its parameter or optimiser "
                             "structure differs from this one's); delete it to start afresh")
        new = []
        for i, x in enumerate(leaves):
            a = z[f"leaf_{i}"]
            if a.shape != np.shape(x) or a.dtype != np.asarray(x).dtype:
                raise ValueError(f"{path}: leaf {i} has shape {a.shape} {a.dtype}, this fit "
                                 f"has {np.shape(x)} {np.asarray(x).dtype}")
            new.append(jnp.asarray(a))
        step, history = int(z["step"]), [float(v) for v in z["history"]]
    return (*jax.tree.unflatten(treedef, new), step, history)
