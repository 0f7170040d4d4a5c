"""Whitted ray tracing, unrolled to a static depth (notes, "Ray tracing").

    color trace(ray):
        hit = intersectScene(ray)
        if hit:  color = directIllumination(hit)
                         + c_refl · trace(reflected ray)      if hit is reflective
                         + c_trans · trace(refracted ray)     if hit is transmissive
        else:    color = background

With `recursion = "unrolled"` (the default on a GPU) the recursion is unrolled in Python
to `settings.max_depth`: level k of the ray tree is one batch of rays (vmapped), each
with a weight (the product of the c_refl/c_trans along its path), traced and shaded
together; level k + 1 holds their children. With "scan" (the default elsewhere,
`_trace_tree_scan`) the same tree is one `lax.scan` over its slots. The tree
is static and has only the branches that the scene's materials can produce
(`ray_tree`): no transmissive material, no refracted rays (one ray per level); no
reflective or transmissive material, no secondary level at all, whatever max_depth;
no dispersive material, one RGB band. Rays whose parent missed, hit a material that
does not spawn them, or underwent total internal reflection are dead: they keep their
slot in the batch but stop at their first step and add nothing.

intersectScene is `intersect_scene`: the sphere-traced SDF `scene.surface` and every
height field of `scene.heightfields` (marched as in the notes); the nearest hit wins.
After the march, one bounded loop with one copy of f and ∇f polishes the SDF's hit
(Newton) and takes the normal and material at the root (`trace.newton_march`; in the
unrolled "plain" form the normal keeps an evaluation of its own), and one more settles
the origins of the rays it spawns (`spawn_origin`).

Precision (notes, "Precision"): a secondary ray starts `spawn_offset` = ray_offset ·
(ε + 8 ulp·max|pᵢ|) off the surface, on the side it leaves (the viewer's side for
reflection and shadow rays, the far side for refraction), settled by `spawn_origin` on
the level set f = ±offset so that near edges and corners it also clears the ε band of
the neighbouring faces: it neither re-hits the surface it leaves nor starts on the
wrong side (tests/test_precision.py: no re-hit among ~4·10⁵ rays spawned from
spheres, boxes and tori at scales 10⁻³–10³ in float32). Rays that start inside an object march
|f| (`sphere_trace`), so the same ε finds where they leave it.

Media: a refracted ray that enters a `Dielectric` carries its absorption σ_a until it
leaves, and every segment it travels is weighted by exp(−σ_a t) (Beer–Lambert). The
outside medium is vacuum (nested dielectrics are not modelled). Shadow rays treat every
surface as opaque (Whitted 1980: no caustics through glass).

Kernels handle one camera ray; `render` vmaps them.
"""

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .bsdf.dispatch import dispatch
from .bsdf.scattering import reflect, refract
from .heightfield import HeightField
from .kinds import group_by_kind, lookup, stack
from .lights import shadow_ray
from .march import SphereTracing, form, tape
from .march.sphere import rounding_floor
from .march.search import repeat
from .trace import (hit_epsilon, intersect_plane, normal_and_material, sphere_trace,
                    value_and_gradient)
from .vecmath import dot, normalize, safe_div, safe_norm, stop_gradient, to_local


def select(values, index):
    """values[index] for a static list of equally shaped arrays and a traced index.

    A chain of `where`s rather than a gather: the same under vmap, and a plain
    elementwise program for the lane-wise backends (`jaxrt.kernels`).
    """
    out = values[0]
    for k in range(1, len(values)):
        out = jnp.where(index == k, values[k], out)
    return out


def spawn_offset(p, settings, epsilon=None):
    """Distance that a secondary ray starts off the surface at `p`.

    ray_offset · (ε + 8 · machine-epsilon · max|pᵢ|), where ε is the hit epsilon in
    effect at the hit (settings.hit_epsilon by default; with a pixel epsilon, the
    epsilon of the pixel cone at the hit distance). The first term puts the origin
    beyond the band |f| < ε in which the marcher declares a hit (ray_offset = 4 leaves a
    margin of 3ε for the curvature of the surface and the error of the hit point), so
    the new ray does not re-hit the surface it leaves, also when it starts inside an
    object. The second is the rounding error of the hit point's coordinates (a few ulps
    of the largest), so that the offset also works far from the origin (pbrt-v4
    `OffsetRayOrigin` bounds the same error per coordinate; `rounding_floor`, with no
    gradient).
    """
    eps = settings.hit_epsilon if epsilon is None else epsilon
    return settings.ray_offset * (eps + rounding_floor(p))


def surface_distance(scene, which, x):
    """Distance bound of surface `which` (0: the SDF, scaled by 1/L; k: height field
    k − 1) at x: the function whose ε band the marchers test."""
    values = [scene.surface(x) / scene.surface.lipschitz().astype(x.dtype)]
    values += [field.eval(x)[0] for field in scene.heightfields]
    return select(values, which)


def spawn_origin(scene, which, p, n, offset, side, steps=2):
    """Origin of a secondary ray that leaves surface `which` at p along the side of the
    unit normal n (n points to where the ray goes: outward for a reflection seen from
    outside, inward for a refraction into the object, …); side = +1 if that is the
    outside of the surface, −1 the inside.

    x₀ = p + offset · n, then `steps` (settings.spawn_steps) Newton steps towards the
    level set f(x) = side · offset of the surface's distance bound f:
    x ← x − (f(x) − side · offset) ∇f / |∇f|².
    Along a smooth surface x₀ is already there and the steps change nothing; near an
    edge or a corner, where another face of the same surface is nearer than `offset`,
    they push the origin out of that face's ε band too, where the ray would otherwise
    re-hit it at t = 0 (one step per face that can be nearer than the offset: two settle
    the edges and corners of boxes, a third face is then already ≥ offset away). The
    correction carries no gradient (the origin's gradient is that of p). p, n, offset
    and side may carry a leading batch axis (several origins from one hit share one
    compiled step).
    """
    x0 = p + jnp.asarray(offset)[..., None] * n
    if steps == 0:
        return x0
    batched = p.ndim > 1
    settle = partial(_settle, steps=steps)
    settle = jax.vmap(settle, (None, None, 0, 0)) if batched else settle
    # Through the tape: the settled origin is a record (a bounded loop, no gradient).
    x = tape.march(settle, stop_gradient(scene), which, jax.lax.stop_gradient(x0),
                   jax.lax.stop_gradient(side * offset))
    return x0 + jax.lax.stop_gradient(x - x0)


def _settle(scene, which, x, target, steps):
    """`steps` Newton steps x ← x − (f(x) − target) ∇f / |∇f|² towards the level set
    f = target of surface `which` (no gradient): one loop, so that the program holds one
    copy of f and ∇f whatever `steps`."""
    def f_and_grad(q):
        return value_and_gradient(lambda x: surface_distance(scene, which, x), q)

    def body(_, x):
        f, g = f_and_grad(x)
        return x - safe_div(f - target, dot(g, g)) * g

    return repeat(steps, body, x)


def direct_lighting(scene, p, n, wo, material, settings, colour=None, active=True, origin=None):
    """Σ_lights f(wo, wi) · E · cos θi · V  +  ambient, at point p with normal n (facing wo).

    Each kind of light answers for all its lights (`illuminate` in a `lax.scan` over
    their stacked parameters: wi, distance and E of every light, no SDF); the sum then
    runs over the lights of every kind in one `lax.scan`, whose step evaluates the
    material (once per material kind, `bsdf.dispatch`) and traces the shadow ray: one
    copy of both in the program whatever the number and the kinds of lights.

    f is the material's BRDF in the local frame of n; E the light's irradiance
    (I / r² for point lights); V the shadow-ray visibility. `colour` turns RGB values
    into the colour representation of the render (RGB: identity; spectral: the value
    at one wavelength), applied to f and E separately. Inactive lanes trace no shadow
    ray (it stops at its first step). Shadow rays start at `origin` (default
    p + spawn_offset · n; the integrator passes `spawn_origin`).
    """
    colour = _rgb if colour is None else colour
    wo_local = to_local(wo, n)
    origin = p + spawn_offset(p, settings) * n if origin is None else origin
    # ambient() may come in the default float dtype (Material's zeros): cast to p's.
    radiance = colour(dispatch(scene.materials, material, lambda m: m.ambient().astype(p.dtype)))
    if not scene.flags("has_diffuse"):
        return radiance

    def step(radiance, light):
        wi, dist, irradiance = light
        cos_i = dot(wi, n)
        wi_local = to_local(wi, n)
        f = dispatch(scene.materials, material, lambda m: m.eval(wo_local, wi_local),
                     jnp.zeros(3, p.dtype), lambda m: m.has_diffuse)
        lit = active & (cos_i > 0.0)
        dist = jnp.where(lit, dist, 0.0)
        visible = visibility(scene, origin, wi, dist, settings)
        return radiance + jnp.where(lit, colour(f) * colour(irradiance) * cos_i * visible, 0.0), None

    # (wi, distance, E) of every light, kind by kind, then one `lax.scan` over all of
    # them: one shadow march and one material evaluation in the program. Through the
    # tape, so that the shadow marches' records leave the scan as its outputs.
    incident = [jax.lax.scan(lambda c, light: (c, light.illuminate(p)), None, stack(lights))[1]
                for _, lights in group_by_kind(list(scene.lights))]
    if incident:
        lights = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs).astype(p.dtype), *incident)
        radiance, _ = tape.scan(step, radiance, lights)
    return radiance


def _rgb(x):
    return x


def _select_material(materials, predicate, fn, default, material):
    """fn(m) for the material with index `material` if predicate(m), else `default`;
    fn is evaluated once per kind of material with the predicate (`bsdf.dispatch`)."""
    return dispatch(materials, material, fn, default, predicate)


class SceneHit(NamedTuple):
    """The nearest hit of a ray in a scene (`intersect_scene`).

    t         distance to the hit (t_max on a miss); differentiable where it hits.
    hit       the ray hit the SDF surface or a height field.
    steps     marching steps of the sphere tracer plus those of every height field.
    normal    [3] unit outward normal at the hit (SDF gradient, or the height field's
              (−∂h/∂x, 1, −∂h/∂z) normal, pointing up).
    material  index of the material hit (int32).
    surface   which surface was hit (int32): 0 the SDF, k the height field k − 1.
    inside    the ray started inside the surface it hit (below the height field): it
              leaves the solid there. A ray that started outside arrives from outside,
              whatever the sign of the computed normal (`shade_ray`).
    """

    t: jnp.ndarray
    hit: jnp.ndarray
    steps: jnp.ndarray
    normal: jnp.ndarray
    material: jnp.ndarray
    surface: jnp.ndarray
    inside: jnp.ndarray


def intersect_scene(scene, origin, direction, settings, cone=None, t_max=None):
    """intersectScene of the notes: the nearest of the sphere-traced SDF `surface` and
    of every height field (marched by `HeightField.intersect`). One ray."""
    surface = scene.surface
    planes = analytic_planes(surface) if getattr(settings, "analytic_planes", False) else []
    # The normal at the hit from the Newton loop's copy of f where it runs as a loop. The
    # "plain" form unrolls that loop, and there a third unrolled iteration made the Warp
    # scene's Pallas program larger (2977 → 3129 lane operations) and its render on an
    # H100 slower (0.93 → 1.07 ms) than an evaluation of its own.
    in_loop = settings.normal_mode == "autodiff" and form.current() != "plain"
    hit = sphere_trace(surface, origin, direction, settings, cone=cone, t_max=t_max,
                       fields=("steps", "inside") + (MEET_FIELDS if planes else ()),
                       normal=in_loop)
    t, found, steps, inside = hit.t, hit.hit, hit.steps, hit.inside
    meets = ()
    if planes:
        t, found, meets = _meet_planes(planes, origin, direction, hit, settings, t_max)
    if hit.normal is None:
        normal, material = normal_and_material(surface, origin + t * direction, settings)
    else:  # the Newton loop's, or a met plane's at its analytic t (the last met is nearest)
        normal, material = hit.normal, hit.material
        for plane, meet in zip(planes, meets):
            normal = jnp.where(meet, normalize(plane.normal), normal)
            material = jnp.where(meet, plane.material, material)
    which = jnp.zeros((), jnp.int32)
    for k, field in enumerate(scene.heightfields):
        h = field.intersect(origin, direction, settings, cone=cone, t_max=t_max)
        nearer = h.hit & ((~found) | (h.t < t))
        t = jnp.where(nearer, h.t, t)
        normal = jnp.where(nearer, field.normal(origin + h.t * direction), normal)
        material = jnp.where(nearer, field.material, material)
        which = jnp.where(nearer, k + 1, which)
        inside = jnp.where(nearer, h.inside, inside)
        found = found | h.hit
        steps = steps + h.steps
    material = jnp.clip(material, 0, len(scene.materials) - 1)
    return SceneHit(t, found, steps, normal, material, which, inside)


#: Analytic planes are met up to this many max_distances away: the floor then reaches
#: within (camera height) / (10⁴ · max_distance) radians of the horizon, far below a
#: pixel, and p stays far from float overflow.
PLANE_HORIZON = 1e4

#: A ray out of budget glides along a plane if the plane's distance at its last sample
#: is the scene's f there to within the rounding floor of f at that point
#: (`march.sphere.rounding_floor`) plus this fraction of f (the march keeps f / L: the
#: round trip through the Lipschitz factor).
GLIDE_RTOL = 1e-5

#: The `sphere_trace` fields that `_meet_planes` reads.
MEET_FIELDS = ("exhausted", "last_t", "last_d")


def analytic_planes(surface):
    """The `sdf.Plane`s at the top of the scene's surface (the surface itself, or children
    of its top-level `Union`): those that `intersect_scene` also meets analytically."""
    from .sdf import Plane, Union
    from .sdf.stack import StackedUnion

    if isinstance(surface, Plane):
        return [surface]
    if isinstance(surface, (Union, StackedUnion)):
        return [c for c in surface.children() if isinstance(c, Plane)]
    return []


def _meet_planes(planes, origin, direction, hit, settings, t_max):
    """Ray–plane intersection (notes; `trace.intersect_plane`) for the rays that the march
    `hit` (a `trace.Hit` with `MEET_FIELDS`) let go where nothing can lie between its
    last sample and the plane. Returns (t, found, meets): `meets[k]` where plane k was
    met nearer than the planes before it (the last plane met is the nearest).

    Met (the nearest such plane at its analytic t, where 0 < t < PLANE_HORIZON ·
    max_distance):
    - a ray that escaped: its march stepped beyond t_max (max_distance) without a hit.
      The march never passes a surface, so nothing lies before t_max; the plane, met
      beyond it, is what the ray sees up to the horizon (what lies between t_max and the
      plane is not marched: an object beyond max_distance is not seen, the floor is).
    - a ray out of budget gliding along the plane: at its last sample (`Hit.last_t`) the
      plane is the nearest surface, its distance there the scene's f to within the
      rounding floor of f at that point (+ GLIDE_RTOL · f), and the plane's t lies beyond
      `last_t`. A ray grazing a floor converges on it too slowly for its budget; the
      analytic t is where it was going.
    Not met:
    - a ray out of budget whose last sample is nearer some other surface than the
      plane (it crawled past a near miss, or was approaching another object): what lies
      between its last sample and the plane was never marched, so the ray stays a miss
      (issue 14: such rays saw the floor through the objects in between);
    - rays that start inside a solid, dead rays (t_max = 0), rays that hit.
    What remains: a gliding ray out of budget is carried across the unmarched rest of
    its path, so an object standing on the floor ahead of it (between its last sample
    and the plane's t) is not seen; nor is one beyond max_distance in front of the floor.

    No extra march or SDF evaluation of the scene: one plane distance per plane at the
    last sample. Differentiable in the plane, the origin and the direction (through the
    analytic t; the conditions carry no gradient)."""
    t, found = hit.t, hit.hit
    limit = jnp.asarray(settings.max_distance if t_max is None else t_max, t.dtype)
    far = PLANE_HORIZON * settings.max_distance
    free = (~found) & (~hit.inside) & (limit > 0.0)
    escaped = free & (~hit.exhausted)
    last_t, last_d = stop_gradient(hit.last_t), stop_gradient(hit.last_d)
    last = stop_gradient(origin) + last_t * stop_gradient(direction)
    tol = rounding_floor(last) + GLIDE_RTOL * jnp.abs(last_d)
    met = jnp.zeros_like(found)
    meets = []
    for plane in planes:
        n = plane.normal / jnp.sqrt(dot(plane.normal, plane.normal))
        t_p, ok = intersect_plane(origin, direction, n, plane.offset)
        d_p = stop_gradient(plane).distance(last)
        gliding = free & hit.exhausted & (jnp.abs(d_p - last_d) <= tol) & (t_p > last_t)
        meet = (escaped | gliding) & ok & (t_p < far) & ((~met) | (t_p < t))
        t = jnp.where(meet, t_p, t)
        met = met | meet
        meets.append(meet)
    return t, found | met, tuple(meets)


def visibility(scene, origin, wi, distance, settings):
    """Visibility in [0, 1] of a light at `distance` along `wi`: `lights.shadow_ray`
    against the SDF surface (hard, soft or none), times 0/1 for each height field that
    the shadow ray crosses first (height fields cast hard shadows)."""
    visible = shadow_ray(scene.surface, origin, wi, distance, settings)
    if settings.shadows == "none" or not scene.heightfields:
        return visible
    t_max = jnp.minimum(distance, settings.shadow_max_distance or settings.max_distance)
    quick = SphereTracing.of(settings, newton_steps=0)
    for field in scene.heightfields:
        # Only whether it crosses: no interpolation or refinement of the crossing.
        field = HeightField(field.height, field.material, field.max_steps, field.min_step,
                            field.rel_step, interpolate=False, refine_steps=0)
        blocked = field.intersect(origin, wi, quick, t_max=t_max).hit
        visible = jnp.where(blocked, 0.0, visible)
    return visible


# -- the static ray tree ------------------------------------------------------------


class RayTree(NamedTuple):
    """The static shape of the ray tree of one camera ray.

    branches     children of each hit: () or ("reflect",) or ("reflect", "transmit")
                 (or ("transmit",)).
    depth        levels of secondary rays (max_depth, or 0 without branches).
    direct       some material is lit directly (shadow rays are traced).
    wavelengths  wavelength samples (0: RGB rendering).
    """

    branches: tuple
    depth: int
    direct: bool
    wavelengths: int

    def rays_per_level(self):
        """Batch size of each level: b^k for b branches."""
        return [len(self.branches) ** k for k in range(self.depth + 1)]


def ray_tree(scene, settings, spectral=None):
    """The `RayTree` that `trace_radiance` unrolls for `scene` and `settings`.

    Reflected rays exist if some material `has_reflection`, refracted ones if some
    `has_transmission`; depth is `settings.max_depth` if either exists, else 0.
    Spectral rendering (`settings.wavelengths` samples) only if some material
    `is_dispersive` and wavelengths > 0 (with wavelengths = 0 a dispersive scene is
    rendered in RGB, its indices at the d line); `spectral=True` forces it, for tests
    and comparisons, `spectral=False` forces RGB. In spectral mode the camera ray does
    not depend on the wavelength, so it is traced once; its children, per wavelength.
    """
    branches = tuple(name for name, flag in (("reflect", "has_reflection"),
                                             ("transmit", "has_transmission"))
                     if scene.flags(flag))
    depth = settings.max_depth if branches else 0
    if spectral is None:
        spectral = scene.flags("is_dispersive") and settings.wavelengths > 0
    elif spectral and settings.wavelengths < 3:
        raise ValueError(f"spectral rendering needs RenderSettings.wavelengths ≥ 3, got {settings.wavelengths}")
    wavelengths = settings.wavelengths if spectral else 0
    return RayTree(branches, depth, scene.flags("has_diffuse"), wavelengths)


class Ray(NamedTuple):
    """One ray of the tree (or, with a leading batch axis, one level of it).

    origin [3], direction [3] (unit), cone [2] (pixel cone r0, spread), weight [C]
    (product of the c_refl/c_trans along the path; C = 3 for RGB, 1 per wavelength),
    sigma [C] (absorption coefficient of the medium the ray travels in), alive (bool:
    dead rays stop at their first step and add nothing).
    """

    origin: jnp.ndarray
    direction: jnp.ndarray
    cone: jnp.ndarray
    weight: jnp.ndarray
    sigma: jnp.ndarray
    alive: jnp.ndarray


def camera_ray(origin, direction, cone=None, channels=3):
    """The root `Ray` of a tree: weight 1, outside any medium."""
    dtype = origin.dtype
    cone = jnp.zeros(2, dtype) if cone is None else cone
    return Ray(origin, direction, cone, jnp.ones(channels, dtype), jnp.zeros(channels, dtype),
               jnp.ones((), bool))


def aovs_of(dtype):
    """The AOVs of one `shade_ray` as shapes: every AOV is of the ray's dtype, the depth,
    step count and coverage scalars, the normal and albedo 3-vectors."""
    scalar, vector = jax.ShapeDtypeStruct((), dtype), jax.ShapeDtypeStruct((3,), dtype)
    return {"depth": scalar, "normal": vector, "albedo": vector, "steps": scalar,
            "coverage": scalar}


class Shaded(NamedTuple):
    """What `shade_ray` returns for one ray.

    radiance  [C] weight · exp(−σ t) · (direct light at the hit, or background).
    children  {branch name: Ray} for the branches of the tree ({} at the last level).
    aovs      {"depth", "normal", "albedo", "steps", "coverage"} of this hit.
    """

    radiance: jnp.ndarray
    children: dict
    aovs: dict


def shade_ray(scene, ray, settings, tree=None, colour=None, wavelength=None, spawn=True):
    """Trace one `Ray`, shade its hit and spawn its children (one node of the tree).

    The reflected child starts `spawn_offset` off the surface on the viewer's side
    along r = 2 (n·wo) n − wo; the refracted child on the far side along
    `refract(wo, n, eta)`, dead under total internal reflection. Weights: the parent's
    throughput times the material's c_refl / c_trans (`specular`). `tree`: the static
    `RayTree` (default `ray_tree(scene, settings)`); `colour`: RGB → render colour
    (default identity); `wavelength`: nm, for dispersive indices (None: RGB).
    """
    tree = ray_tree(scene, settings) if tree is None else tree
    colour = _rgb if colour is None else colour
    o, d, cone = ray.origin, ray.direction, ray.cone
    dtype = o.dtype
    t_max = jnp.where(ray.alive, jnp.asarray(settings.max_distance, dtype), 0.0)
    hit = intersect_scene(scene, o, d, settings, cone=cone, t_max=t_max)
    found = hit.hit & ray.alive
    p = o + hit.t * d
    material = hit.material
    # Which side the ray arrives from is known from where it started (outside the solid:
    # it enters), not from the sign of the computed normal: at |f| within rounding of 0
    # the gradient of an SDF of the form sign(s)·sqrt(d) (the exact cone, say) can point
    # either way, and a normal taken as inward made the hit "exiting": its shadow rays
    # started inside the solid and the pixel went black (the showcase cone's speckles).
    n = jnp.where(dot(hit.normal, d) <= 0.0, hit.normal, -hit.normal)  # faces the viewer
    entering = ~hit.inside  # the ray arrives from outside
    n_out = jnp.where(entering, n, -n)  # outward
    wo = -d

    offset = spawn_offset(p, settings, hit_epsilon(settings, hit.t, cone))
    spawning = spawn and bool(tree.branches)
    # Origins of secondary rays: on the viewer's side (shadow and reflected rays; the
    # outside iff the ray arrived from outside) and on the far side (refracted rays).
    sides = []
    if tree.direct or (spawning and "reflect" in tree.branches):
        sides.append(1.0)
    if spawning and "transmit" in tree.branches:
        sides.append(-1.0)
    origins = {}
    if sides:
        toward = jnp.asarray(sides, dtype)
        outside = jnp.where(entering, toward, -toward)
        starts = spawn_origin(scene, hit.surface, jnp.broadcast_to(p, (len(sides), 3)),
                              toward[:, None] * n, jnp.broadcast_to(offset, (len(sides),)), outside,
                              steps=settings.spawn_steps)
        origins = {side: starts[k] for k, side in enumerate(sides)}
    above, below = origins.get(1.0), origins.get(-1.0)
    if tree.direct:
        local = direct_lighting(scene, p, n, wo, material, settings, colour, active=found,
                                origin=above)
    else:
        local = colour(dispatch(scene.materials, material, lambda m: m.ambient().astype(dtype)))
    radiance = jnp.where(found, local, jnp.where(ray.alive, colour(scene.background), 0.0))
    # Beer–Lambert along the segment (σ = 0 outside any medium).
    throughput = ray.weight * jnp.exp(-ray.sigma * hit.t)

    albedo = dispatch(scene.materials, material, lambda m: m.base_color())
    zero3 = jnp.zeros(3, dtype)
    aovs = {
        "depth": hit.t,
        "normal": jnp.where(found, n, zero3),
        "albedo": jnp.where(found, albedo, zero3),
        "steps": hit.steps,
        "coverage": found,
    }
    aovs = {k: jnp.asarray(v, dtype) for k, v in aovs.items()}  # as `aovs_of` says
    children = {}
    if spawning:
        children = _spawn(scene, settings, tree, colour, wavelength, ray, hit, found, p,
                          n_out, n, entering, material, throughput, above, below)
    return Shaded(throughput * radiance, children, aovs)


def _spawn(scene, settings, tree, colour, wavelength, ray, hit, found, p, n_out, n, entering,
           material, throughput, above, below):
    dtype = p.dtype
    wo = -ray.direction
    zeros = jnp.zeros(3, dtype)
    specular = lambda m: m.has_reflection or m.has_transmission  # noqa: E731
    c_refl, c_trans, eta = _select_material(
        scene.materials, specular, lambda m: m.specular(dot(n_out, wo), wavelength),
        (zeros, zeros, jnp.ones((), dtype)), material)
    cone = jnp.stack([ray.cone[0] + ray.cone[1] * hit.t, ray.cone[1]])
    children = {}
    if "reflect" in tree.branches:
        spawns = lookup([m.has_reflection for m in scene.materials], material)
        alive = found & spawns
        wr = reflect(wo, n)
        weight = throughput * colour(c_refl) * _offset_absorption(ray.sigma, above, p, wr)
        children["reflect"] = Ray(above, wr, cone, jnp.where(alive, weight, 0.0), ray.sigma, alive)
    if "transmit" in tree.branches:
        spawns = lookup([m.has_transmission for m in scene.materials], material)
        wt, valid = refract(wo, n_out, eta)
        inside = _select_material(scene.materials, lambda m: m.has_transmission,
                                  lambda m: getattr(m, "absorption", zeros), zeros, material)
        # Entering: the medium of the material; leaving: vacuum.
        sigma = jnp.where(entering, colour(inside), 0.0)
        alive = found & spawns & valid
        weight = throughput * colour(c_trans) * _offset_absorption(sigma, below, p, wt)
        children["transmit"] = Ray(below, wt, cone, jnp.where(alive, weight, 0.0), sigma, alive)
    return children


def _offset_absorption(sigma, origin, p, direction):
    """exp(−σ ℓ): Beer–Lambert over the part of the path that a child's own t does not
    include because it starts at an offset origin. The origin is moved off the surface
    by δ = origin − p (along the normal), so the path from the surface to the child's
    starting plane along d is ℓ = |δ|² / (δ·d) = offset / cos θ (exact for a flat
    surface; the cosine floored at 1/4, beyond which the offset's share of any path is
    negligible). Without it, a slab of thickness L seen at θ is attenuated over
    (L − offset) / cos θ. No gradient: the offset is a precision device, not geometry."""
    delta = jax.lax.stop_gradient(origin - p)
    along = jnp.maximum(dot(delta, jax.lax.stop_gradient(direction)), 0.0)
    length = safe_div(dot(delta, delta), jnp.maximum(along, 0.25 * safe_norm(delta)))
    return jnp.exp(-sigma * length)


def _trace_tree(scene, origin, direction, cone, settings, tree, colour, channels, wavelength):
    """Radiance added by each level [depth + 1, channels] of one camera ray's tree, and
    the AOVs of its first hit."""
    if settings.ray_tree_form() == "scan" and tree.depth > 0:
        return _trace_tree_scan(scene, origin, direction, cone, settings, tree, colour,
                                channels, wavelength)
    rays = jax.tree_util.tree_map(lambda x: x[None], camera_ray(origin, direction, cone, channels))
    levels = []
    aovs = None
    for level in range(tree.depth + 1):
        spawn = level < tree.depth

        def shade(ray, spawn=spawn):
            return shade_ray(scene, ray, settings, tree, colour, wavelength, spawn)

        gather = None
        if level > 0 and wavelength is None:  # a replay shades the live rays alone
            gather = (lambda ray: ray.alive, _dead_shade(tree, spawn))
        out = tape.vmap(shade, gather)(rays)
        levels.append(jnp.sum(out.radiance, axis=0))
        if level == 0:
            aovs = jax.tree_util.tree_map(lambda x: x[0], out.aovs)
        if spawn:
            # [B, b, ...] -> [B·b, ...]: the children of ray i are rays b·i … b·i + b − 1.
            children = [out.children[name] for name in tree.branches]
            rays = jax.tree_util.tree_map(
                lambda *xs: jnp.stack(xs, axis=1).reshape((-1,) + xs[0].shape[1:]), *children)
    return jnp.stack(levels), aovs


def _trace_tree_scan(scene, origin, direction, cone, settings, tree, colour, channels, wavelength):
    """`_trace_tree` as one `lax.scan` over the slots of the tree
    (`settings.ray_tree_form()` = "scan", the default on a CPU).

    The tree is stored in heap order: slot 0 is the camera ray and the b children of
    slot i are slots b·i + 1 … b·i + b, so level k occupies slots Σ_{j<k} b^j onwards
    (the same static tree as the unrolled levels). Step i shades slot i and writes its
    children after it; leaves (the last level) write into b scratch slots at the end.
    Every step is the same computation, compiled once whatever the depth; each traces
    one ray per camera ray (a batch over the pixels under `render`'s vmap). On "fused"
    a block of rays skips a slot that is dead for all of them (`tape.cond`): most slots,
    where few pixels see a mirror or glass; the replay of its record shades a slot only
    for the rays alive in it (`tape._gathered`; in RGB only: a spectral tree's branch
    closes over the sample's wavelength).
    """
    b = len(tree.branches)
    sizes = tree.rays_per_level()
    slots = sum(sizes)
    first_leaf = slots - sizes[-1]
    level_of = jnp.asarray(np.repeat(np.arange(len(sizes)), sizes), jnp.int32)
    root = camera_ray(origin, direction, cone, channels)
    buffer = jax.tree_util.tree_map(
        lambda x: jnp.zeros((slots + b,) + x.shape, x.dtype).at[0].set(x), root)

    def shade(ray):
        return shade_ray(scene, ray, settings, tree, colour, wavelength, True)

    dead = _dead_shade(tree)
    aovs = dead(root).aovs
    levels = jnp.zeros((len(sizes), channels), origin.dtype)

    # Vmapped (the "jax" backend, the replay), `ray` (slot i) is read from the buffer at
    # the end of the step before, after its write: XLA:CPU copies a buffer that a step
    # reads and then updates whole, in every step (O(slots²): on the glass scene's 127
    # slots the replay took 1.5 s against 0.6 s), and the children are written with
    # `_write_slots`, whose transpose does not copy it either. The lane kernels read it
    # first: on "fused" the other order rendered the glass scene in 17.0 s against
    # 10.4 s, and Pallas (which unrolls the scan) was not measured with it.
    ahead = tape.lane_backend() is None
    write = _write_slots if ahead else jax.lax.dynamic_update_slice_in_dim

    def read(buffer, i):
        return jax.tree_util.tree_map(lambda x: x[i], buffer)

    def step(carry, i):
        buffer, ray, levels, aovs = carry
        ray = ray if ahead else read(buffer, i)
        out = tape.cond(ray.alive, shade, dead, ray, gather=wavelength is None)
        levels = levels.at[level_of[i]].add(out.radiance)
        aovs = jax.tree_util.tree_map(lambda a, x: jnp.where(i == 0, x, a), aovs, out.aovs)
        children = [out.children[name] for name in tree.branches]
        start = jnp.where(i < first_leaf, b * i + 1, slots)
        buffer = jax.tree_util.tree_map(
            lambda buf, *xs: write(buf, jnp.stack(xs), start, 0), buffer, *children)
        return (buffer, read(buffer, i + 1) if ahead else None, levels, aovs), None

    init = (buffer, root if ahead else None, levels, aovs)
    (_, _, levels, aovs), _ = tape.scan(step, init, jnp.arange(slots))
    return levels, aovs


def _dead_shade(tree, spawn=True):
    """`dead(ray)`: what `shade_ray` gives a dead ray (no radiance, dead children, zero
    AOVs), without shading it. The children keep the ray's own (unit) direction, so they
    stay finite."""

    def dead(ray):
        weight = jnp.zeros_like(ray.weight)
        child = Ray(ray.origin, ray.direction, ray.cone, weight, ray.sigma, jnp.zeros((), bool))
        aovs = {k: jnp.zeros(a.shape, a.dtype) for k, a in aovs_of(ray.origin.dtype).items()}
        return Shaded(weight, {name: child for name in tree.branches} if spawn else {}, aovs)

    return dead


def _write_slots(buffer, x, start, axis):
    """`lax.dynamic_update_slice_in_dim(buffer, x, start, axis)` for a slot buffer of the
    scan tree, where the slots written hold zeros (or, the leaves' scratch slots, are
    never read into the result): its tangent is
    `ḃuffer + dynamic_update_slice(0, ẋ, start)`, an addition whose transpose passes the
    cotangent through and slices ẋ's out, so the gradient's scan updates its cotangent
    buffer in place. The plain rule's transpose zeroes the written slots of the
    cotangent, after reading them, and XLA:CPU then copied the whole buffer twice in
    every step (O(slots²): a 127-slot tree of 19 200 rays took 7.4 s against 1.9 s).
    Integer and boolean buffers (no tangent) take the plain update."""
    if not jnp.issubdtype(buffer.dtype, jnp.inexact):
        return jax.lax.dynamic_update_slice_in_dim(buffer, x, start, axis)
    return _write_zero_slots(buffer, x, start, axis)


@partial(jax.custom_jvp, nondiff_argnums=(3,))
def _write_zero_slots(buffer, x, start, axis):
    return jax.lax.dynamic_update_slice_in_dim(buffer, x, start, axis)


@_write_zero_slots.defjvp
def _write_zero_slots_jvp(axis, primals, tangents):
    buffer, x, start = primals
    d_buffer, d_x, _ = tangents
    d_x = jax.lax.dynamic_update_slice_in_dim(jnp.zeros_like(d_buffer), d_x, start, axis)
    return _write_zero_slots(buffer, x, start, axis), d_buffer + d_x


def trace_radiance(scene, origin, direction, cone, settings, spectral=None):
    """Radiance and AOVs of one camera ray, through the Whitted ray tree of `ray_tree`.

    Returns a dict: rgb [3] (linear), depth (hit distance; max_distance on a miss),
    normal [3] (world space, facing the camera; 0 on a miss), albedo [3], steps,
    coverage (1 on a hit, 0 on a miss). The AOVs are those of the first hit.
    `spectral`: None (spectral only for dispersive scenes), True or False (forced).
    """
    levels, aovs = trace_levels(scene, origin, direction, cone, settings, spectral)
    return {"rgb": jnp.sum(levels, axis=0), **aovs}


def trace_levels(scene, origin, direction, cone, settings, spectral=None):
    """Linear RGB added by each level of the ray tree, [depth + 1, 3], and the AOVs.

    Level k holds the rays after k specular bounces; the render at max_depth = d is
    the sum of the first d + 1 levels of any deeper tree (shading a level does not
    depend on how deep the tree goes).
    """
    tree = ray_tree(scene, settings, spectral)
    if tree.wavelengths == 0:
        return _trace_tree(scene, origin, direction, cone, settings, tree, _rgb, 3, None)
    return _trace_spectral(scene, origin, direction, cone, settings, tree)


def _trace_spectral(scene, origin, direction, cone, settings, tree):
    """Spectral rendering: the tree is traced once per wavelength sample (vmapped), every
    RGB quantity (BRDF values, light colours, tints, absorption, background) becomes its
    value at λ through the linear basis of `spectral.rgb_to_spectrum`, dispersive indices
    are evaluated at λ, and the N radiances become linear sRGB (`spectrum_to_rgb`).

    The N samples are stratified over 380–780 nm with one jitter per camera ray (a hash
    of the ray, constant in the scene parameters), so neighbouring pixels sample
    different wavelengths: banding becomes noise that averages out with `spp`.
    """
    from . import spectral

    dtype = origin.dtype
    jitter = _ray_hash(jax.lax.stop_gradient(origin), jax.lax.stop_gradient(direction))
    lambdas = spectral.sample_wavelengths(tree.wavelengths, jitter.astype(dtype))

    def one(lam):
        basis = jnp.stack([spectral.rgb_to_spectrum(e, lam[None])[0]
                           for e in jnp.eye(3, dtype=dtype)])

        def colour(x):
            return jnp.dot(basis, x)[None]

        return _trace_tree(scene, origin, direction, cone, settings, tree, colour, 1, lam)

    values, aovs = tape.vmap(one)(lambdas)  # [N, depth + 1, 1]
    to_rgb = spectral.spectral_rgb_matrix(lambdas).astype(dtype)  # [3, N]
    levels = values[..., 0].T @ to_rgb.T  # [depth + 1, 3]
    return levels, jax.tree_util.tree_map(lambda x: x[0], aovs)


def _ray_hash(origin, direction):
    """A pseudo-random number in [0, 1) from a ray (the shader hash fract(sin(x)·43758.5453))."""
    x = jnp.dot(direction, jnp.array([12.9898, 78.233, 37.719], direction.dtype)) * 1e3 \
        + jnp.dot(origin, jnp.array([3.7, 11.3, 5.1], origin.dtype))
    h = jnp.sin(x) * 43758.5453
    return jnp.clip(h - jnp.floor(h), 0.0, 0.999999)
