"""Silhouette-aware pixel coverage: antialiased outlines whose position has a gradient.

The problem. A point-sampled pixel that sees a surface on one side of an outline and
the background (or a farther surface) on the other changes by a jump when the outline
crosses its sample; between jumps it does not depend on where the outline is. So the
gradient of any image loss with respect to a parameter that moves an outline (a
sphere's radius, an object's position, seen against what lies behind it) is zero,
though the image mean clearly depends on it. `RenderSettings(silhouette=False)`, the
default, has exactly this behaviour: shading inside the outlines is differentiated,
outlines are not.

The estimator (`RenderSettings(silhouette=True)`): pixel coverage from the closest
approach of each camera ray to the surface it nearly misses.

1. The sphere tracer records the ray's nearest near miss: the sample where the
   cone-relative distance f / r(t) has a local minimum (r(t) = cone[0] + cone[1]·t, half
   a pixel at distance t), with the samples before and after it (`Hit.closest_*`). The
   final approach to a hit is not a near miss, so a ray that hits a floor just behind a
   sphere still reports the sphere.
2. The minimum is refined by golden-section search on f/r in that bracket (no
   gradient; `GOLDEN_STEPS` evaluations), giving t*, p* = o + t* d.
3. The distance from the ray to the surface, d* = f(p*) / |∇f(p*)| (first order; exact
   for distance functions), is measured in pixels with the pixel footprint
   s* = |Jᵀ n*|, J = ∂(o + t* d)/∂(px, py) the camera's ray Jacobian and n* the unit
   normal at p* (so off-axis pixels of a wide lens are measured correctly), and turned
   into coverage by a smooth ramp outside the outline:

       α = ramp(d* / (W s*)),  ramp(u) = 1 − u²/2 (u ≤ 1), (2 − u)²/2 (1 ≤ u ≤ 2), 0,
       W = silhouette_width / sqrt(spp).

   −ramp' is a tent of base 2: tents of base 2 sum to 1 at unit spacing for every
   offset, so pixel centres sample the ramp's derivative correctly along outlines at
   any sub-pixel position (a linear ramp one pixel wide gives ±20 % along a short
   outline).
4. The pixel blends what a sample just inside the outline sees over what the ray sees:

       L = α · L_in + (1 − α) · L(ray),

   L_in the radiance of a ray aimed INSIDE_AIM pixel inside the outline point p_s
   nearest p*, traced and shaded like any camera ray (`trace_radiance`, reflections and
   refractions included) from its entry point (`inner_hit`).

Gradients. α carries the derivative of the outline's position: d* changes as the
camera moves the ray (∇f(p*)·∂p*) and as the shape moves the surface near p_s
(∂f/∂θ / |∇f| there: for distance functions the same as at p*, for bounds such as smooth
blends only the surface gives the surface's speed). Moving the outline by δ pixels
changes α by ramp'·δ/W for every sample in the ramp, and the samples of each image row
crossed at angle φ sum ramp' to 1/cos φ, so a row changes by δ/cos φ · (L_in − L_out):
the change of the exact box-filtered row. By the envelope theorem d* needs no
derivative of t* (f/r is stationary there). A sample at distance d outside an outline of
curvature κ₀ lies on an offset curve 1 + κ₀ d times longer than the outline, so the
gradient of α (not its value) is scaled by 1 − d κ, κ the apparent curvature of the
level-set contour at p* (`contour_curvature`; 0 for straight edges, 1/d around a
corner, whose offset arc then gets no weight). The inner ray sees the surface held
fixed: at a grazing point its hit slides as 1/cos θ when the surface moves, a derivative
that belongs to a sliver of the pixel far thinner than α; its colour keeps the
gradients of materials, lights and camera. The ray's own radiance keeps all its
(interior) gradients.

Where the outline's derivative goes (`RenderSettings.silhouette_gradient`). "ramp"
(default): on the ramp's samples, 0 to 2W pixels outside the outline, the exact
derivative of the estimator's own image. "outline": each ramp sample's term
∂α · (L_in − L_out) is added to the pixel that holds its outline point, d*/s* pixels
inwards along the image-space normal Jᵀn* (`outline_offset`, `splat_outline`), so the
image's derivative is that of a box-filtered image, whose pixels change where the
outline crosses them. A loss whose values are box-filtered (a photograph, or a
straight-through loss I_sil + stop_gradient(I_box − I_sil)) then weighs the outline's
derivative with its residual at the outline, inside which an object that is too large
has its residual; "ramp" weighs it with the residual up to 2W pixels outside, where
there is none, so too large an object shrinks several times too weakly
(tests/test_silhouette.py, docs/inverse.md).

What it approximates, and its bias.
- The image: the ramp lies wholly outside the outline (samples that hit count as fully
  covered, since their distance to the outline is not known), so outlines are dilated
  by W pixels on average (∫ ramp = 1): antialiased, but objects look W pixels larger.
  Fitting to images rendered with the same settings cancels this (both sides are
  dilated alike); fitting to photographs sees objects W pixels too large.
- The gradient of an image region's mean: exact to first order for outlines that are
  straight or have the curvature `contour_curvature` measures, and shading that is
  smooth across them. The ends of outline segments (box corners) are resolved to the
  sample spacing, as in point sampling: ±0.5 px per end at 1 spp, less with more
  samples (tests use spp = 4).
- Shading discontinuities inside an outline (a crease between two faces of different
  brightness, a shadow edge, a material boundary) are not outlines: their gradients
  are zero, as without the estimator.
- One near miss per sample (the nearest): outlines of two surfaces closer than 2W
  pixels to each other in the image are blended as if only the nearer were there.
- L_in is one sample INSIDE_AIM pixel inside the outline (on a smooth surface the
  normal there is tilted towards the viewer by sqrt(2 · INSIDE_AIM / ρ), ρ the outline's
  radius of curvature in pixels).
- Rays that start inside a surface have no near misses (α = 0).
- With spp > 1 the samples are jittered, so the ramp's derivative is no longer summed
  on a lattice: gradients are unbiased but noisier; image outlines converge to the
  exact ones as W / sqrt(spp) → 0.
The tests (tests/test_silhouette.py) check the gradient of region means crossed by
outlines (a sphere's radius, a box's position, a smooth blend's width) against finite
differences of renders with 32×32 samples per pixel, and against the exact derivative
of a disc's area.

Cost: a second march of the camera ray, a golden-section search, a Hessian of f, a
projection and a regula falsi, and one more camera ray (traced and shaded) per sample:
about 2.5× the time of a render without it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .march import SphereTracing, tape
from .march.silhouette import (EDGE_OFFSET, GOLDEN_STEPS, ILLINOIS_STEPS, INSIDE_AIM,  # noqa: F401
                               PROJECT_STEPS, inner_hit, project_to_surface, refine_closest)
from .trace import evaluated, sphere_trace, stop_gradient, value_and_gradient
from .vecmath import dot, normalize, safe_div, safe_norm

def ramp(u):
    """Coverage at u = d / (W · pixel) outside an outline: the quadratic B-spline step

        α(u) = 1 − u²/2 (0 ≤ u ≤ 1),  (2 − u)²/2 (1 ≤ u ≤ 2),  0 (u ≥ 2),

    whose derivative −α' is the tent of unit area on [0, 2]. Tents of base 2 sum to 1
    at unit spacing whatever their offset (a partition of unity), so pixel centres
    sample this ramp's derivative correctly along an outline of any position; the
    derivative of a linear (box) ramp one pixel wide is sampled by 1 or 2 pixels per row
    depending on sub-pixel offsets, ±20 % over a short outline.
    """
    u = jnp.clip(u, 0.0, 2.0)
    return jnp.where(u < 1.0, 1.0 - 0.5 * u * u, 0.5 * (2.0 - u) ** 2)


def contour_curvature(sdf, p, direction):
    """Apparent curvature of the contour through `p` of the level set of f, seen along
    `direction` (no gradient).

    Koenderink 1984 ("What does the occluding contour tell us about solid shape?"):
    κ_app = K / κ_r, with K the Gaussian curvature of the level surface at p and κ_r its
    normal curvature along the view direction. With the second fundamental form
    II = tᵀ H t / |∇f| (H the Hessian of f) in the tangent basis (v, e), v the view
    direction projected on the tangent plane and e = n × v:
    κ_app = II_ee − II_ve² / II_vv (II_ee where |II_vv| is ~0).
    """
    _, grad, hess = value_grad_hessian(sdf, p)
    return _curvature(grad, hess, stop_gradient(direction))


def value_grad_hessian(sdf, p):
    """(f, ∇f, H) at p, no gradient: forward over `trace.value_and_gradient` (reverse
    mode, or forward mode in a Pallas program), whose inner pass also gives f and ∇f, so
    the program holds one copy of f for all three."""
    sdf, p = stop_gradient((sdf, p))

    def value_and_grad(q):
        f, g = value_and_gradient(lambda x: sdf(x), q)
        return g, (f, g)

    hess, (f, grad) = jax.jacfwd(value_and_grad, has_aux=True)(p)
    return f, grad, hess


def _curvature(grad, hess, direction):
    """κ_app of `contour_curvature` from ∇f and the Hessian H at p."""
    g = jnp.sqrt(dot(grad, grad))
    n = normalize(grad)
    v = normalize(direction - dot(direction, n) * n)
    e = normalize(jnp.cross(n, v))
    inv_g = safe_div(1.0, g)
    ii_vv = dot(v, hess @ v) * inv_g
    ii_ee = dot(e, hess @ e) * inv_g
    ii_ve = dot(v, hess @ e) * inv_g
    ok = jnp.abs(ii_vv) > 1e-9 * (jnp.abs(ii_ee) + jnp.abs(ii_ve) + 1e-300)
    return ii_ee - jnp.where(ok, ii_ve * ii_ve / jnp.where(ok, ii_vv, 1.0), 0.0)


def coverage(sdf, origin, direction, cone, jacobian, hit, settings):
    """(α, valid, p_s, n_s, r*, outline) of the ray's nearest near miss.

    α = ramp(d* / (W · s*)), 0 where the ray has no near miss or starts inside a
    surface. d* is the distance from p* = o + t* d to the surface, with the gradient
    of how the outline moves: ∇f(p*)·∂p*/|∇f(p*)| as the camera moves the ray, and
    −v_n = ∂f(p_s; θ)/∂θ / |∇f(p_s)| as the shape moves the surface at p_s, the surface
    point nearest p* (for a distance function the two evaluation points give the same
    ∂f/∂θ; for bounds such as smooth blends only the surface point gives the speed of
    the surface). s* = |Jᵀ n*| is the pixel footprint: `jacobian` = (∂o/∂(px, py),
    ∂d/∂(px, py)), [3, 2] each, and at t* the ray point moves by J = ∂o + t* ∂d per
    pixel, s* of which towards the surface (world units per pixel). The gradient of α
    (not its value) is scaled by the length ratio 1 − d* κ (κ the apparent curvature
    of the level-set contour at p*) of the outline and the offset curve the sample
    lies on. p_s, its unit normal n_s, r* = r(t*) (the cone radius) and `outline`
    (`outline_offset`: the outline's position in the image relative to the sample)
    carry no gradient.
    """
    dtype = origin.dtype
    t_star = tape.march(refine_closest, sdf, origin, direction, cone, hit)
    p_star = origin + t_star * direction
    # f, ∇f and the Hessian at p* from one evaluation (no gradient); f(p*) then gets the
    # camera part of its gradient to first order, f + ∇f · (p* − p̂*) (value f, since
    # p* − p̂* = 0; derivative ∇f · ∂p*, that of f(p*) with the shape held fixed).
    p_hat = jax.lax.stop_gradient(p_star)
    f, grad, hess = value_grad_hessian(sdf, p_hat)
    f = f + dot(grad, p_star - p_hat)
    grad_norm = safe_norm(grad)
    n = normalize(grad)
    radius = jax.lax.stop_gradient(cone[0] + cone[1] * t_star)  # half a pixel at t*
    d_origin, d_direction = jacobian
    image_normal = (d_origin + t_star * d_direction).T @ n  # ∂(distance)/∂(px, py)
    footprint = safe_norm(image_normal)
    width = settings.silhouette_width / jnp.sqrt(jnp.asarray(settings.spp, dtype))
    valid = ((~hit.inside) & (t_star > 0.0) & (radius > 0.0) & (grad_norm > 0.0)
             & (footprint > 0.0))
    # Camera part: f(p*) with the shape held fixed.
    distance = safe_div(f, jnp.where(valid, grad_norm, 1.0))
    # Shape part: the surface's own displacement near p_s (value 0), evaluated a
    # little outside it (EDGE_OFFSET), where the distance to a sharp edge still has
    # the direction of n* (on the edge itself either face's gradient may be taken).
    p_s = tape.march(project_to_surface, sdf, p_star, n)
    offset = jax.lax.stop_gradient(EDGE_OFFSET * (distance + 2.0 * radius))
    # f and ∇f of the shape held fixed, then f with the shape's derivative from a JVP
    # (`evaluated`): differentiating `value_and_gradient`'s value differentiated its
    # reverse pass too, NaN at a box's outline when compiled at XLA:CPU -O0.
    q_s = p_s + offset * n
    f_s, grad_s = value_and_gradient(lambda q: stop_gradient(sdf)(q), q_s)
    f_s = evaluated(sdf, q_s, f_s)
    norm_s = jnp.sqrt(dot(grad_s, grad_s))
    ok_s = norm_s > 0.0
    distance = distance + jnp.where(
        ok_s, (f_s - jax.lax.stop_gradient(f_s)) / jnp.where(ok_s, norm_s, 1.0), 0.0)
    alpha = ramp(safe_div(distance, width * jnp.where(valid, footprint, 1.0)))
    # Offset-curve correction of the gradient: a sample at distance d outside an
    # outline of curvature κ₀ lies on a curve 1 + κ₀ d = 1 / (1 − κ d) times longer.
    kappa = _curvature(grad, hess, jax.lax.stop_gradient(direction))
    scale = jax.lax.stop_gradient(jnp.clip(1.0 - distance * kappa, 0.0, 2.0))
    alpha = jax.lax.stop_gradient(alpha) + scale * (alpha - jax.lax.stop_gradient(alpha))
    alpha = jnp.where(valid, alpha, 0.0)
    n_s = jnp.where(ok_s, normalize(grad_s), n)
    outline = outline_offset(distance, image_normal, footprint, width, valid)
    return alpha, valid, p_s, n_s, radius, outline


def outline_offset(distance, image_normal, footprint, width, valid):
    """Where the outline lies in the image, from the sample (pixels, no gradient): the
    sample is d*/s* pixels outside it along the image-space normal Jᵀn*/s*, so the
    outline is at −d* · Jᵀn* / s*²; its length is clipped to the ramp's 2W (0 where the
    sample has no near miss)."""
    offset = -safe_div(distance, jnp.where(valid, footprint, 1.0) ** 2) * image_normal
    length = safe_norm(offset)
    offset = offset * jnp.minimum(1.0, safe_div(2.0 * width, length))
    return jax.lax.stop_gradient(jnp.where(valid & jnp.all(jnp.isfinite(offset)), offset, 0.0))


def blend(scene, camera, xy, out, settings):
    """Apply the estimator to the `trace_radiance` result `out` of the camera ray through
    continuous pixel position `xy` = (px, py).

    rgb ← α · L(inner ray) + (1 − α) · rgb; coverage ← coverage + α · (1 − coverage).
    The inner ray starts at its entry point (`inner_hit`), so that the integrator
    finds its hit at once. The other AOVs stay those of the ray itself. Called by
    `render` when `settings.silhouette` is on.
    """
    from .integrator import trace_radiance

    origin, direction, cone = camera.generate_ray(xy[0], xy[1])
    jacobian = jax.lax.stop_gradient(
        jax.jacfwd(lambda q: camera.generate_ray(q[0], q[1])[:2])(xy))
    # The camera ray's march again (its near miss is not in `out`); no polishing.
    march = SphereTracing.of(settings, newton_steps=0)
    hit = sphere_trace(scene.surface, origin, direction, march, cone=cone,
                       fields=("inside", "closest_t", "closest_bracket"))
    alpha, valid, p_s, n_s, radius, outline = coverage(
        scene.surface, origin, direction, cone, jacobian, hit, settings)
    entry, aim, found = tape.march(lambda *a: inner_hit(*a, settings), scene.surface, origin,
                                   p_s, n_s, radius)
    use = valid & found
    alpha = jnp.where(use, alpha, 0.0)
    t_entry = jax.lax.stop_gradient(dot(entry - origin, aim))
    inner_cone = jnp.stack([cone[0] + cone[1] * t_entry, cone[1]])
    start = jnp.where(use, entry, jax.lax.stop_gradient(origin))
    aim = jnp.where(use, aim, jax.lax.stop_gradient(direction))
    # The inner sample sits at a grazing point of the surface, where its hit point
    # slides fast as the surface moves (dt/dθ ∝ 1/cos θ): that derivative belongs to
    # a sliver of the pixel much thinner than α, so the inner ray sees the surface
    # held fixed; its colour keeps the gradients of materials, lights and camera.
    frozen = eqx.tree_at(lambda s: s.surface, scene, stop_gradient(scene.surface))
    inner = trace_radiance(frozen, start, aim, inner_cone, settings)
    result = dict(out)
    contrast = inner["rgb"] - out["rgb"]
    if settings.silhouette_gradient == "outline":
        # α's derivative (where the outline is) goes to the outline's own pixels
        # (`splat_outline`); the rest of the gradient stays with the sample.
        result["rgb"] = out["rgb"] + jax.lax.stop_gradient(alpha) * contrast
        result[OUTLINE_RGB] = (alpha - jax.lax.stop_gradient(alpha)) * jax.lax.stop_gradient(contrast)
        result[OUTLINE_XY] = jax.lax.stop_gradient(xy) + jnp.where(use, outline, 0.0)
    else:
        result["rgb"] = out["rgb"] + alpha * contrast
    result["coverage"] = out["coverage"] + alpha * (1.0 - out["coverage"])
    return result


# The per-sample outputs of `blend` with silhouette_gradient = "outline": the outline
# term (value 0, derivative ∂α · (L_in − L_out)) and the outline's image position.
OUTLINE_RGB, OUTLINE_XY = "outline_rgb", "outline_xy"


def splat_outline(values, xy, height, width, spp):
    """The outline terms `values` [N, C] of N = H·W·spp samples, each added to the pixel
    that holds its outline's image position `xy` [N, 2] (continuous pixels; positions
    outside the image are dropped), averaged over the pixel's spp samples: [H, W, C].

    Linear in `values` (whose value is 0), so it adds nothing to the image; its
    derivative is that of the box-filtered image as its outline moves: a box-filtered
    pixel changes by the outline's normal speed integrated over the part of the outline
    inside it, and the ramp's samples of a row, whose derivatives sum to the outline's
    (`ramp`), land on the pixels that part crosses, not on the ramp's samples up to 2W
    pixels outside it. Its transpose reads an image cotangent at each sample's outline.
    """
    col, row = jnp.floor(xy[:, 0]).astype(jnp.int32), jnp.floor(xy[:, 1]).astype(jnp.int32)
    inside = (row >= 0) & (row < height) & (col >= 0) & (col < width)
    image = jnp.zeros((height, width, values.shape[-1]), values.dtype)
    return image.at[jnp.clip(row, 0, height - 1), jnp.clip(col, 0, width - 1)].add(
        jnp.where(inside, 1.0 / spp, 0.0)[:, None] * values)
