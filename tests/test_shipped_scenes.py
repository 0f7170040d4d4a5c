"""The shipped scenes render clean, and the glass they show matches closed forms.

The water box of configs/scenes/glass_spheres.toml used to rest *exactly* on the floor
plane: the box's bottom face and the plane coincided, so the union of the two had no
surface there (inside the box is next to inside the floor), and every refracted ray that
went down through the water travelled on into the solid floor: blocky black and
background-coloured cells along the bottom of the box. The box now stands 0.01 above the
floor (more than the spawn offset, 4·ε, and far more than ε); the closed form below checks
the box's optics, and `test_no_coincident_faces_in_shipped_scenes` the scene files.

Artefact counts (`jaxrt.artefacts`, issue 14): NaN pixels, black speckles and outline
holes (a background pixel with ≥ 3 hit 4-neighbours where a render with 8× the step
budget hits). The showcase's ~24 black speckles on the orange cone (480×270) were hits
shaded as seen from inside: the integrator took the side a ray arrives from from the
sign of the computed normal, and the exact cone's gradient at |f| within rounding of 0
can point inward; the shadow rays then started inside the cone. It now takes it from
where the ray started (`SceneHit.inside`). The outline holes (camera rays that spent
their budget crawling past a silhouette) were gone before this: the secant finish of
`march.sphere` and the floor's analytic intersection resolve them (0 holes, 0 hit/miss
disagreements with 8× steps at 480×270).

A speckle was first any dark outlier (a hit pixel darker than 0.2× the darkest of its
hit 8-neighbours). The ones left after the cone fix were traced pixel by pixel
(experiments/artefacts/trace_pixel.py) and are shading, not acne. The showcase's: at
both sizes one pixel of a gold cup of the far row, 30° from its neighbours' normal and
off its highlight (f ≈ 0.04 where theirs see ≈ 0.5; it keeps 75–85 % of its radiance
without shadows); at 192×108 two pixels of the rough copper torus (Beckmann α = 0.35)
facing away from both lobes (f ≈ 10⁻⁵ and 3·10⁻³, both shadow rays V = 1); at 96×54
one pixel of the red cavity carved out of the white box, seen through its top opening,
facing away from the directional light and seeing the point light at cos θ = 0.16 past
the rim, 0.008 from it at t = 0.24 (a real penumbra: k·f/(L t) = 0.19 with the union's
Lipschitz bound L = 1.72, V = 0.09; the pixel is a dark outlier without shadows too).
configs/scenes/glass_spheres.toml's three (96×54) are pixels of the water box seen in
the mirror whose paths are trapped in the box by total internal reflection when the
Whitted tree ends (max_depth = 6): black with or without shadows, 0.13–0.4 at depth 10
(converged: the same at 16), the price of the scene's depth dial, not of its shadows.
So a speckle is now a dark outlier that its shadow rays made dark: no dark outlier in
a render with shadows="none" and less than half of its luminance there (the module
docstring of `jaxrt.artefacts`); dark outliers that are dark without shadows too are
counted apart (`dark_shading`) and listed by the test's message. The Warp scene has no
dark outlier at all.

One dark outlier is no shading: glass_spheres at 192×108, pixel (row 54, column 92), is
black with shadows and 0.2 without. Its camera ray passes the glass sphere 1.2 ε from
its silhouette, spends its 192 steps crawling past it (it needs 318) and runs out
receding from it; `integrator._meet_planes` then carried it to the floor plane at
t = 7.27, through the red sphere (t = 5.28) and the mirror, onto the floor behind the
mirror, in the mirror's shadow. The showcase at 192×108 has three such pixels (the floor
seen through the gold cup and the carved box; lit floor, so no speckle): neither counter
saw them, so `artefacts` counts see-through pixels (out of budget and deeper than the
8×-steps reference). At 96×54 no shipped scene has one. Issue 14, fixed: `_meet_planes`
now meets a plane only for a ray that escaped at max_distance or one out of budget
gliding along the plane (the plane the nearest surface at its last sample), so such a
ray stays a miss
(`test_a_ray_out_of_budget_after_a_near_miss_does_not_see_the_floor_through_an_occluder`).
That left the showcase (then 160 steps) with 4 holes at 96×54 (51 at 480×270): camera
rays passing the gold sphere's and the cone's silhouettes within ~4e-4 need up to ~380
steps to crawl past them, and had been carried to the floor, which happened to be what
lay behind. The showcase now has a 400-step budget (0 holes at 96×54, 2 at 480×270).

Under this test's non-strict xfail the showcase had never rendered in the tests: with
jax_enable_x64 on (conftest) its float32 render raised a TypeError (`Plastic.eval` made
a float64 Fresnel term; tests/test_bsdf_models.py now checks every model's dtype).
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import config


def slab_scene(eta, sigma, thickness, background):
    """A slab |z| ≤ thickness/2 of a `Dielectric(eta, absorption=sigma)`, 40 wide, no lights."""
    slab = jr.sdf.Box(half_extents=(20.0, 20.0, thickness / 2.0), material=0)
    return jr.Scene(surface=slab, materials=[jr.bsdf.Dielectric(eta, absorption=sigma)],
                    lights=[], background=background)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("max_depth", [2, 4])
def test_slab_seen_head_on_transmits_the_closed_form(dtype, max_depth):
    """Radiance through a slab seen head-on (notes, "Fresnel"; Beer–Lambert):

    F = ((η − 1)/(η + 1))² at normal incidence at both faces, transmission e^{−σL} per
    crossing. Against a uniform background B, the Whitted tree of depth D sums the paths
    that leave the slab within D bounces: reflected at the front, F; through,
    (1 − F)² e^{−σL}; and at D = 4 also those reflected twice inside,
    (1 − F)² F² e^{−3σL} (through) and (1 − F)² F e^{−2σL} (back out of the front).
    """
    eta, thickness = 1.333, 0.9
    sigma = np.array([0.45, 0.12, 0.06])
    background = np.array([0.55, 0.65, 0.8])
    scene = slab_scene(eta, tuple(sigma), thickness, tuple(background))
    camera = jr.OrthographicCamera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), size=0.5,
                                   width=4, height=4)
    settings = jr.RenderSettings(max_depth=max_depth, shadows="none", dtype=dtype, backend="jax",
                                 max_distance=50.0, aovs=())
    rgb = np.asarray(jr.render(scene, camera, settings).rgb, np.float64)
    f = ((eta - 1.0) / (eta + 1.0)) ** 2
    a = np.exp(-sigma * thickness)
    expected = f + (1.0 - f) ** 2 * a
    if max_depth >= 4:
        expected = expected + (1.0 - f) ** 2 * (f * f * a**3 + f * a * a)
    tol = 2e-6 if dtype == "float64" else 2e-5
    np.testing.assert_allclose(rgb, np.broadcast_to(background * expected, rgb.shape), rtol=tol)


def _faces(node, offset=np.zeros(3)):
    """Axis-aligned extents (lo, hi) of the boxes and the heights of the y-planes in a
    union of translated primitives (what the shipped scenes are made of)."""
    name = type(node).__name__
    if name == "Union":
        for child in node.children_:
            yield from _faces(child, offset)
    elif name == "Translate":
        yield from _faces(node.child, offset + np.asarray(node.offset))
    elif name in ("Box", "RoundBox"):
        h = np.asarray(node.half_extents)
        yield "box", offset - h, offset + h, node.material
    elif name == "Plane":
        n = np.asarray(node.normal) / np.linalg.norm(node.normal)
        if np.allclose(np.abs(n), [0.0, 1.0, 0.0]):
            yield "plane", float(node.offset) * n[1], None, node.material


@pytest.mark.parametrize("path", ["configs/scenes/glass_spheres.toml", "jaxrt/data/showcase.toml"])
def test_no_coincident_faces_in_shipped_scenes(path):
    """No face of a glass box lies on a floor plane (to within 100 hit epsilons): the
    union of the two would have no surface there, and refracted rays would run on into
    the floor. (An opaque box may rest on the floor: its bottom face is never seen.)"""
    scene, _, settings = config.load(path)
    faces = list(_faces(scene.surface))
    floors = [f[1] for f in faces if f[0] == "plane"]
    for kind, lo, hi, material in faces:
        if kind == "box" and scene.materials[material].has_transmission:
            for y in floors:
                assert min(abs(lo[1] - y), abs(hi[1] - y)) > 100 * settings.hit_epsilon, (path, lo, hi, y)


# ---------------------------------------------------------------- artefact counts


def test_the_counters_find_a_speckle_and_a_hole_and_nothing_else():
    """`jaxrt.artefacts`: one dark pixel inside a lit region is a speckle, one missed
    pixel inside a hit region is a hole when the reference hits there (a real gap, one
    the reference misses too, is not); edges of the region and dark regions are neither;
    a pixel whose ray ran out of budget sees through when it sees farther than the
    reference."""
    from jaxrt import artefacts

    h, w = 12, 16
    rgb = np.full((h, w, 3), 0.6)
    rgb[:, 8:] = 0.02  # a dark (shadowed) half: not speckles
    depth = np.full((h, w), 5.0)
    depth[:, :2] = 100.0  # background at the left: its edge is no hole
    rgb[5, 4] = 0.01  # a speckle
    depth[3, 5] = 100.0  # a hole
    depth[8, 5] = 100.0  # a real gap (the reference misses it too)
    hit = artefacts.hit_mask(depth, 100.0)
    reference = depth.copy()
    reference[3, 5] = 5.0
    assert np.argwhere(artefacts.speckle_pixels(rgb, hit)).tolist() == [[5, 4]]
    assert np.argwhere(artefacts.hole_pixels(hit, artefacts.hit_mask(reference, 100.0))).tolist() == [[3, 5]]
    rgb[2, 2] = np.nan
    assert artefacts.nan_pixels(rgb).sum() == 1
    # See-through: rays out of budget that see farther than the reference (the floor at
    # 9 behind a surface at 5, the background); one that hit the same surface is not.
    exhausted = np.zeros((h, w), bool)
    exhausted[[6, 7, 9], [10, 11, 12]] = True
    seen = reference.copy()
    seen[6, 10] = 9.0
    seen[7, 11] = 100.0
    assert np.argwhere(artefacts.see_through_pixels(seen, reference, exhausted)).tolist() == [[6, 10], [7, 11]]


def test_a_pixel_dark_by_its_shading_is_no_speckle_and_one_dark_by_its_shadows_is():
    """`artefacts.speckle_pixels` with the no-shadow reference: of three pixels equally
    darker than their lit neighbours (Y = 0.01 among 0.6), the one as dark without shadows
    (shading: a lobe, a facing) is no speckle; the one that is as bright as its
    neighbours without shadows (acne: its shadow rays took its light) is; the one that
    is a dark outlier without shadows too (0.05 among 0.6, a surface unlike its
    neighbours) is no speckle either but counts as `dark_shading`, for a trace to judge.
    A dark outlier that the shadows darkened by less than half (0.1 of 0.13, no outlier
    without shadows) is no speckle: its shading took it to the edge of the test."""
    from jaxrt import artefacts

    h, w = 12, 16
    rgb = np.full((h, w, 3), 0.6)
    depth = np.full((h, w), 5.0)
    hit = artefacts.hit_mask(depth, 100.0)
    unshadowed = rgb.copy()
    shading, acne, unlike, partly = (3, 3), (3, 9), (8, 3), (8, 9)
    for pixel in (shading, acne, unlike):
        rgb[pixel] = 0.01
    rgb[partly] = 0.1
    unshadowed[shading] = 0.01
    unshadowed[unlike] = 0.05
    unshadowed[partly] = 0.13
    assert np.argwhere(artefacts.dark_outliers(rgb, hit)).tolist() == [[3, 3], [3, 9], [8, 3], [8, 9]]
    assert np.argwhere(artefacts.speckle_pixels(rgb, hit, unshadowed)).tolist() == [list(acne)]
    assert np.argwhere(artefacts.shading_dark_pixels(rgb, hit, unshadowed)).tolist() == [[3, 3], [8, 3]]
    image = jr.Image(rgb=rgb, depth=depth)
    c = artefacts.counts(image, 100.0, unshadowed=unshadowed)
    assert (c["speckles"], c["dark_outliers"], c["dark_shading"]) == (1, 4, 2), c


def _convex_points(shape, scale, rng, count):
    """(sdf, points, outward unit normals) on a sphere or on the side of a cone (the
    showcase's orange cone: radius 0.7, height 1.5), placed as in the showcase."""
    centre = np.array([1.0, 0.0, 1.5])
    phi = rng.uniform(0.0, 2.0 * np.pi, count)
    if shape == "sphere":
        n = rng.normal(size=(count, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        centre = centre + [0.0, 0.8, 0.0]
        return jr.sdf.Sphere(radius=0.7 * scale), centre, 0.7 * n, n
    r, h = 0.7, 1.5
    y = rng.uniform(0.05, 0.95, count) * h
    rho = r * (1.0 - y / h)
    p = np.stack([rho * np.cos(phi), y, rho * np.sin(phi)], 1)
    n = np.stack([h * np.cos(phi), np.full(count, r), h * np.sin(phi)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return jr.sdf.Cone(radius=r * scale, height=h * scale), centre, p, n


@pytest.mark.parametrize("shape", ["sphere", "cone"])
@pytest.mark.parametrize("shadows", ["hard", "soft"])
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_shadow_rays_leaving_a_lit_convex_surface_at_grazing_angles_are_not_self_occluded(
        shape, shadows, scale):
    """A shadow ray from a point of a convex surface towards a light above its tangent
    plane (cos θ from 0.002 to 1) leaves the surface and never comes back: it is not
    blocked (soft: the penumbra term k·f/t of the shape alone is ≥ 1 only where
    k·(offset/t + sin θ) ≥ 1, so the soft test asks V > 0 at grazing angles and V = 1
    from cos θ ≥ 0.1 (k = 10)). Shadow acne is a V = 0 there. float32, the
    integrator's spawn offset."""
    from jaxrt.integrator import spawn_offset
    from jaxrt.lights import shadow_ray
    from jaxrt.render import _cast

    dtype = jnp.float32
    count = 512
    settings = jr.RenderSettings(shadows=shadows, penumbra=10.0, hit_epsilon=1e-4 * scale,
                                 max_distance=60.0 * scale, shadow_steps=64, dtype="float32")
    rng = np.random.default_rng(3)
    shape_sdf, centre, local, n = _convex_points(shape, scale, rng, count)
    surface = _cast(jr.sdf.Translate(shape_sdf, offset=tuple(centre * scale)), jnp.dtype(dtype))
    p = (centre + local) * scale
    # wi: cos θ = n·wi from 0.002 to 1, in a random tangent direction.
    cos = np.geomspace(2e-3, 1.0, count)
    tangent = np.cross(n, rng.normal(size=(count, 3)))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    wi = cos[:, None] * n + np.sqrt(1.0 - cos[:, None] ** 2) * tangent

    def one(p, n, wi):
        origin = p + spawn_offset(p, settings) * n
        return shadow_ray(surface, origin, wi, jnp.asarray(20.0 * scale, dtype), settings)

    v = np.asarray(jax.jit(jax.vmap(one))(*(jnp.asarray(a, dtype) for a in (p, n, wi))))
    if shadows == "hard":
        assert np.all(v == 1.0), cos[v < 1.0]
    else:
        assert np.all(v > 0.0), cos[v <= 0.0]
        assert np.all(v[cos >= 0.1] == 1.0), cos[(cos >= 0.1) & (v < 1.0)]


@pytest.mark.parametrize("scale", [1.0, 1e3])
def test_height_field_in_large_units_with_a_tiny_epsilon_keeps_its_hits(scale):
    """A sine height field scaled by 10³ (amplitude, wavelength, camera; min_step by s)
    with hit_epsilon = 1e-9 · s (below float32's precision) hits every ray that the
    same field hits at scale 1, at the same relative depth."""
    from jaxrt.heightfield import HeightField, SineHeight
    from jaxrt.render import _cast

    dtype = jnp.float32
    field = HeightField(SineHeight(amplitude=0.2 * scale, frequency=(1.5 / scale, 1.0 / scale)),
                        min_step=0.01 * scale)
    field = _cast(field, jnp.dtype(dtype))
    settings = jr.RenderSettings(hit_epsilon=1e-9 * scale, max_distance=100.0 * scale, dtype="float32")
    u = np.linspace(-0.6, 0.6, 24)
    x, y = np.meshgrid(u, u - 0.5)
    d = np.stack([x.ravel(), y.ravel(), -np.ones(x.size)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile([0.0, 2.0 * scale, 4.0 * scale], (x.size, 1))
    hits = jax.jit(jax.vmap(lambda o, d: field.intersect(o, d, settings)))(jnp.asarray(o, dtype), jnp.asarray(d, dtype))
    hit, t = np.asarray(hits.hit), np.asarray(hits.t) / scale
    down = d[:, 1] < -0.3  # steep enough to meet the field well within max_distance
    assert hit[down].all()
    # The reference at scale 1 in float64 (the same field, unscaled).
    field64 = _cast(HeightField(SineHeight(amplitude=0.2, frequency=(1.5, 1.0)), min_step=0.01), jnp.dtype(jnp.float64))
    ref = jax.jit(jax.vmap(lambda o, d: field64.intersect(o, d, jr.RenderSettings(max_distance=100.0))))(
        jnp.asarray(o / scale), jnp.asarray(d))
    assert np.array_equal(hit, np.asarray(ref.hit))
    np.testing.assert_allclose(t[hit], np.asarray(ref.t)[hit], rtol=1e-4)


def test_a_ray_out_of_budget_after_a_near_miss_does_not_see_the_floor_through_an_occluder():
    """A camera ray that passes a unit sphere 1.2 ε from its surface (sphere tracing then
    crawls: ~sqrt(2R/δ) steps on each side of the closest approach) and runs out of its
    budget there must not be carried to the floor plane behind the sphere of radius 0.3
    that lies across its path (its analytic t, `trace.intersect_sphere`): it hits that
    sphere (at its analytic t) or, out of budget, nothing. The floor is met analytically
    (`RenderSettings.analytic_planes`) only where nothing can lie in between."""
    from jaxrt.integrator import intersect_scene
    from jaxrt.render import _cast
    from jaxrt.trace import intersect_plane, intersect_sphere

    eps = 1e-4
    o = np.array([0.0, 0.5, -5.0])
    d = np.array([0.0, -0.04, 1.0]) / np.linalg.norm([0.0, -0.04, 1.0])
    # The grazed sphere: radius 1, its centre 1 + 1.2 ε from the ray at t = 3 (above it).
    side = np.cross(d, [1.0, 0.0, 0.0])
    side = side if side[1] > 0 else -side
    grazed = o + 3.0 * d + (1.0 + 1.2 * eps) * side
    blocker = o + 6.0 * d  # the occluder, centred on the ray at t = 6
    scene = jr.Scene(surface=jr.sdf.Union(
        jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=0),
        jr.sdf.Translate(jr.sdf.Sphere(radius=1.0, material=0), offset=tuple(grazed)),
        jr.sdf.Translate(jr.sdf.Sphere(radius=0.3, material=0), offset=tuple(blocker))),
        materials=[jr.bsdf.Lambert()], lights=[])
    scene = _cast(scene, jnp.dtype(jnp.float64))
    t_floor = float(intersect_plane(jnp.asarray(o), jnp.asarray(d), jnp.array([0.0, 1.0, 0.0]), 0.0)[0])
    t_blocker = float(intersect_sphere(jnp.asarray(o), jnp.asarray(d), jnp.asarray(blocker), 0.3)[0])
    assert t_blocker < t_floor
    for max_steps in (48, 96, 1024):
        settings = jr.RenderSettings(max_steps=max_steps, hit_epsilon=eps, max_distance=40.0,
                                     dtype="float64")
        hit = intersect_scene(scene, jnp.asarray(o), jnp.asarray(d), settings)
        if max_steps == 1024:  # a budget that passes the near miss finds the occluder
            assert bool(hit.hit) and abs(float(hit.t) - t_blocker) < 1e-3, (max_steps, hit.t)
        assert not bool(hit.hit) or abs(float(hit.t) - t_blocker) < 1e-3, (max_steps, float(hit.t), t_blocker)


def test_a_ray_out_of_budget_gliding_along_the_floor_meets_it_at_the_analytic_t():
    """A ray that descends onto the floor at a slope of 1/100 from 0.6 above it converges
    on it geometrically (each step closes 1 % of the rest of the way) and runs out of
    budget gliding, the floor the nearest surface at its last sample; the floor's t (60)
    lies beyond max_distance, so the secant finish cannot take it there. It still meets
    the floor at the analytic t (`trace.intersect_plane`), as does a budget that lets it
    escape at max_distance, and one that, with max_distance beyond the floor, lets the
    secant finish the march. A sphere off the path keeps the surface a union."""
    from jaxrt.integrator import intersect_scene
    from jaxrt.render import _cast
    from jaxrt.trace import intersect_plane, sphere_trace

    o = np.array([0.0, 0.6, 0.0])
    d = np.array([0.0, -0.01, 1.0]) / np.linalg.norm([0.0, -0.01, 1.0])
    scene = jr.Scene(surface=jr.sdf.Union(
        jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=0),
        jr.sdf.Translate(jr.sdf.Sphere(radius=1.0, material=0), offset=(5.0, 1.0, 10.0))),
        materials=[jr.bsdf.Lambert()], lights=[])
    scene = _cast(scene, jnp.dtype(jnp.float64))
    o, d = jnp.asarray(o), jnp.asarray(d)
    t_floor = float(intersect_plane(o, d, jnp.array([0.0, 1.0, 0.0]), 0.0)[0])
    assert 59.0 < t_floor < 61.0
    for max_steps, max_distance, how in ((48, 40.0, "exhausted"), (1024, 40.0, "escaped"),
                                         (48, 100.0, "hit")):
        settings = jr.RenderSettings(max_steps=max_steps, max_distance=max_distance,
                                     dtype="float64")
        march = sphere_trace(scene.surface, o, d, settings)
        assert bool(march.hit) == (how == "hit") and bool(march.exhausted) == (how == "exhausted"), how
        hit = intersect_scene(scene, o, d, settings)
        assert bool(hit.hit), how
        np.testing.assert_allclose(float(hit.t), t_floor, rtol=1e-9 if how != "hit" else 1e-6, err_msg=how)


ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ["jaxrt/data/showcase.toml"] + sorted(
    str(p.relative_to(ROOT)) for p in (ROOT / "configs" / "scenes").glob("*.toml"))


def shipped_counts(path, width=96, height=54, reference_steps=8):
    """`jaxrt.artefacts.counts` of the scene file at a small size with its own settings
    and backend ("auto": the fused lanes on a CPU, or "jax" where it falls back; "backend"
    in the result says which ran). The references are rendered only where they can
    change a count: the holes are judged against a render with `reference_steps`× the
    step budget if some outline candidate or some ray out of budget exists (holes and
    see-through pixels are among them), the speckles against a render with
    shadows="none" if some dark outlier exists (likewise)."""
    import warnings

    from jaxrt import artefacts

    scene, camera, settings = config.load(ROOT / path, width=width, height=height, spp=1)
    settings = settings.replace(aovs=("depth", "steps"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = jr.render(scene, camera, settings)
    fell_back = any("rendering with backend='jax'" in str(w.message) for w in caught)
    hit = artefacts.hit_mask(image.depth, settings.max_distance)
    reference = unshadowed = None
    exhausted = np.asarray(image.steps) > settings.max_steps
    if artefacts.outline_candidates(hit).any() or exhausted.any():
        reference = jr.render(scene, camera, settings.replace(max_steps=settings.max_steps * reference_steps))
    if artefacts.dark_outliers(image.rgb, hit).any():
        unshadowed = jr.render(scene, camera, settings.replace(shadows="none"))
    out = {"holes": 0, "see_through": 0, "dark_shading": 0}  # none without candidates
    out.update(artefacts.counts(image, settings.max_distance, reference, unshadowed, settings.max_steps))
    out["backend"] = "jax (auto fell back)" if fell_back else settings.backend
    if unshadowed is not None:
        speckles = artefacts.speckle_pixels(image.rgb, hit, unshadowed.rgb)
        out["speckles at"] = np.argwhere(speckles).tolist()
        out["dark_shading at"] = np.argwhere(artefacts.shading_dark_pixels(image.rgb, hit, unshadowed.rgb)).tolist()
    return out


@pytest.mark.slow
@pytest.mark.parametrize("path", SHIPPED)
def test_shipped_scenes_render_without_nans_speckles_or_holes(path):
    """Issue 14: the showcase and every scene in configs/scenes render with 0 NaN, 0
    black-speckle, 0 outline-hole and 0 see-through pixels by `jaxrt.artefacts`' counts (96×54, the
    scene's own backend and settings; see the module docstring for what the dark
    pixels that are not speckles are)."""
    c = shipped_counts(path)
    assert (c["nan"], c["speckles"], c["holes"], c["see_through"]) == (0, 0, 0, 0), c


def test_a_cone_lit_from_the_eye_has_no_black_pixels():
    """Every visible point of a cone lit from the camera (a directional light along the
    view, hard shadows, float32) faces the light and sees it: no hit pixel is black. The
    exact cone's gradient at |f| within rounding of 0 can point inward; when the integrator
    took the hit's side from that sign, such hits were shaded as seen from inside the
    solid (shadow rays started inside it): black speckles (the showcase's orange cone)."""
    from jaxrt import artefacts

    eye = np.array([0.0, 5.2, 10.5])
    scene = jr.Scene(surface=jr.sdf.Translate(jr.sdf.Cone(radius=0.7, height=1.5), offset=(1.0, 0.0, 1.5)),
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.4, 0.1))],
                     lights=[jr.DirectionalLight(direction=tuple(eye - [1.0, 0.75, 1.5]))],
                     background=(0.3, 0.36, 0.45))
    camera = jr.PerspectiveCamera(eye=tuple(eye), target=(1.0, 0.75, 1.5), fov=12.0, width=96, height=96)
    settings = jr.RenderSettings(shadows="hard", max_steps=160, backend="jax", dtype="float32",
                                 max_depth=0, aovs=("depth", "normal"))
    image = jr.render(scene, camera, settings)
    hit = artefacts.hit_mask(image.depth, settings.max_distance)
    view = np.asarray(image.normal) @ (np.asarray(scene.lights[0].direction) / np.linalg.norm(scene.lights[0].direction))
    facing = hit & (view > 0.05)
    assert facing.sum() > 2000
    lum = artefacts.luminance(image.rgb)
    assert np.all(lum[facing] > 0.0), np.argwhere(facing & (lum <= 0.0))
