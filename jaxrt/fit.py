"""Image losses and optimistix-driven fitting of scene, material, light and camera
parameters to target images (inverse rendering).

A fit is three choices: which leaves are free (`free_parameters`), how an image is
compared with the target (`l2_loss`, `l1_loss`, or `image_residuals` for least
squares), and which optimistix solver moves the free leaves (`fit` for minimisers,
default BFGS; `fit_least_squares` for Gauss–Newton/Levenberg–Marquardt on residuals,
whose Jacobian JAX builds by forward mode, one pass per free scalar). The whole fit is
one compiled program: the renderer is traced once inside the solver's loop.

    params, rebuild = jr.fit.free_parameters(
        scene, lambda s: (s.surface.child.radius, s.surface.offset))
    target = jr.render(true_scene, camera, settings).rgb
    loss = lambda p, _: jr.fit.l2_loss(jr.render(rebuild(p), camera, settings).rgb, target)
    result = jr.fit.fit(loss, params, optx.BFGS(rtol=1e-8, atol=1e-8))
    fitted_scene = rebuild(result.params)

Outlines only have gradients with `RenderSettings(silhouette=True)` (`jaxrt.silhouette`);
without it a shape's size and position are observable through its shading alone.
"""

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx


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


class FitResult(NamedTuple):
    """params: the fitted values; loss: the objective there; steps: solver steps taken;
    result: the optimistix `RESULTS` (success, or why it stopped); solution: the full
    `optimistix.Solution`."""

    params: Any
    loss: jnp.ndarray
    steps: jnp.ndarray
    result: Any
    solution: Any


def fit(loss_fn, params, solver=None, *, args=None, max_steps=256, throw=False):
    """Minimise `loss_fn(params, args)` (a scalar) over `params` with an optimistix
    minimiser, default `optimistix.BFGS(rtol=1e-6, atol=1e-9)`; gradients by reverse mode.

    `throw=False` returns the last iterate when the solver stops early (max_steps, a
    failed line search); `result.result` says why.
    """
    solver = optx.BFGS(rtol=1e-6, atol=1e-9) if solver is None else solver
    solution = _minimise(loss_fn, solver, params, args, max_steps, throw)
    loss = loss_fn(solution.value, args)
    return FitResult(solution.value, loss, solution.stats["num_steps"], solution.result, solution)


def fit_least_squares(residual_fn, params, solver=None, *, args=None, max_steps=256,
                      throw=False):
    """Minimise ½‖residual_fn(params, args)‖² with an optimistix least-squares solver,
    default `optimistix.LevenbergMarquardt(rtol=1e-6, atol=1e-9)`. The loss reported
    is the mean squared residual."""
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9) if solver is None else solver
    solution = _least_squares(residual_fn, solver, params, args, max_steps, throw)
    r = residual_fn(solution.value, args)
    return FitResult(solution.value, jnp.mean(r * r), solution.stats["num_steps"],
                     solution.result, solution)


@eqx.filter_jit
def _minimise(loss_fn, solver, params, args, max_steps, throw):
    return optx.minimise(loss_fn, solver, params, args=args, max_steps=max_steps, throw=throw)


@eqx.filter_jit
def _least_squares(residual_fn, solver, params, args, max_steps, throw):
    return optx.least_squares(residual_fn, solver, params, args=args, max_steps=max_steps,
                              throw=throw)


def relative_error(fitted, truth):
    """max over leaves of |fitted − truth| / max(|truth|, 1e-12), elementwise."""
    errors = jax.tree_util.tree_map(
        lambda a, b: jnp.max(jnp.abs(a - b) / jnp.maximum(jnp.abs(b), 1e-12)), fitted, truth)
    return jnp.max(jnp.stack(jax.tree_util.tree_leaves(errors)))
