"""Gradients of rendered images: every parameter family against central finite
differences in float64, closed forms, invariances, memory, and the extremes.

The "jax" backend is the reference (its program differentiated as it is); the fast
backends' gradients come from the record/replay of `jaxrt.render` and must equal it
(`Problem.check_replay`, `test_replay_*`).

Interior pixels only: a window of pixels whose 3×3 (5×5 behind glass and mirrors)
neighbourhood sees one material at a continuous depth, so that no outline crosses it
(outlines have their own estimator, tests/test_silhouette.py). Shadows are off: a hard
shadow edge is a discontinuity of the same kind.
"""

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxrt as jr
from jaxrt import sdf, spectral
from jaxrt.bsdf import (GGX, Conductor, CookTorrance, Dielectric, Lambert, Mirror, Phong,
                        SchlickFresnel, Whitted)
from jaxrt.heightfield import GridHeight, HeightField, SineHeight

#: Reference settings: float64, a tight epsilon and three Newton steps, so that the
#: polished hit distance is exact to rounding and finite differences see a smooth image.
FD = jr.RenderSettings(dtype="float64", hit_epsilon=1e-7, newton_steps=3, max_steps=400,
                       shadows="none", batch_size=None, max_depth=0, backend="jax")
RTOL = 1e-4
#: Record/replay gradients against the reference path's, float64.
REPLAY_RTOL = 1e-6


# -- helpers -------------------------------------------------------------------------


def interior_mask(image, erode=1):
    """Pixels whose (2·erode + 1)² neighbourhood sees the same albedo and hit state, with
    normals within 40° of each other and depths within 25 % (no outline, crease or
    occlusion edge nearby)."""
    albedo = np.asarray(image.albedo)
    hit = np.asarray(image.coverage) > 0.5
    depth = np.asarray(image.depth)
    normal = np.asarray(image.normal)
    h, w = hit.shape
    ok = np.zeros((h, w), bool)
    for i in range(erode, h - erode):
        for j in range(erode, w - erode):
            win = (slice(i - erode, i + erode + 1), slice(j - erode, j + erode + 1))
            same = np.all(np.abs(albedo[win] - albedo[i, j]) < 1e-12) and np.all(hit[win] == hit[i, j])
            smooth = (not hit[i, j]) or (
                np.all(np.abs(depth[win] - depth[i, j]) < 0.25 * depth[i, j])
                and np.all(normal[win] @ normal[i, j] > np.cos(np.radians(25.0))))
            ok[i, j] = same and smooth
    return ok


class Problem:
    """loss(x) for the flattened differentiable leaves x of (scene, camera): a fixed
    random weighting of the interior pixels' colours."""

    def __init__(self, scene, camera, settings, erode=1, seed=0, facing=None):
        self.settings = settings
        params, self.static = eqx.partition((scene, camera), eqx.is_inexact_array)
        x0, self.unravel = ravel_pytree(params)
        self.x0 = np.asarray(x0)
        image = jr.render(scene, camera, settings)
        self.mask = interior_mask(image, erode)
        if facing is not None:  # only surfaces within acos(facing) of facing the camera
            self.mask &= np.asarray(image.normal)[..., 2] < -facing
        rng = np.random.default_rng(seed)
        weights = rng.uniform(0.5, 1.5, self.mask.shape) * self.mask / max(self.mask.sum(), 1)
        self.weights = jnp.asarray(weights[..., None] * np.array([0.3, 0.5, 0.2]))
        # Leaves are perturbed outside of any trace (the flat vector is unravelled
        # eagerly), and the gradient is taken of the pytree itself.
        self.params = params
        self.grad_tree = eqx.filter_jit(jax.grad(self._loss_tree))
        leaves = jax.tree_util.tree_flatten_with_path(params)[0]
        self.names = []
        for path, leaf in leaves:
            self.names += [jax.tree_util.keystr(path)] * int(np.size(leaf))

    def _loss_tree(self, params, weights):
        scene, camera = eqx.combine(params, self.static)
        return jnp.sum(jr.render(scene, camera, self.settings).rgb * weights)

    def loss(self, x):
        return float(self._loss_tree(self.unravel(jnp.asarray(x)), self.weights))

    def grad(self, x):
        return ravel_pytree(self.grad_tree(self.unravel(jnp.asarray(x)), self.weights))[0]

    def check_replay(self, backend="auto"):
        """The record/replay gradient (`backend`, whose image is the lane kernel's) equals
        the reference path's: ‖g − g_ref‖ ≤ REPLAY_RTOL ‖g_ref‖, and elementwise."""
        replay = Problem.__new__(Problem)
        replay.__dict__.update(self.__dict__)
        replay.settings = self.settings.replace(backend=backend, batch_size=64)
        replay.grad_tree = eqx.filter_jit(jax.grad(replay._loss_tree))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "auto" may fall back to the vmapped record
            g = np.asarray(replay.grad(self.x0))
        g_ref = np.asarray(self.grad(self.x0))
        assert np.linalg.norm(g_ref) > 0.0
        assert np.linalg.norm(g - g_ref) <= REPLAY_RTOL * np.linalg.norm(g_ref)
        np.testing.assert_allclose(g, g_ref, rtol=REPLAY_RTOL,
                                   atol=REPLAY_RTOL * np.max(np.abs(g_ref)))

    def finite_differences(self, indices, rel_step=1e-5):
        fd = []
        for i in indices:
            h = rel_step * max(1.0, abs(float(self.x0[i])))
            e = np.zeros(self.x0.shape)
            e[i] = h
            fd.append((self.loss(self.x0 + e) - self.loss(self.x0 - e)) / (2 * h))
        return np.array(fd)

    def check(self, family_substrings):
        """For each family (a substring of leaf paths): ‖g − fd‖ ≤ RTOL ‖fd‖."""
        g = np.asarray(self.grad(self.x0))
        report = {}
        for family in family_substrings:
            idx = [i for i, n in enumerate(self.names) if family in n]
            assert idx, f"no parameter matches {family!r}: {sorted(set(self.names))}"
            fd = self.finite_differences(idx)
            err = np.linalg.norm(g[idx] - fd)
            scale = np.linalg.norm(fd)
            report[family] = (err, scale)
        bad = {k: v for k, v in report.items() if not v[0] <= RTOL * v[1] + 1e-12}
        assert not bad, f"gradient ≠ finite differences (error, |fd|): {bad}"
        # Each family must matter in the window (a gradient test of a zero is no test).
        dead = [k for k, (_, s) in report.items() if s < 1e-6]
        assert not dead, f"families with no effect on the window: {dead}"
        return report


# -- depth 0: shapes, placements, materials, lights, camera --------------------------


@pytest.fixture(scope="module")
def placement_problem():
    surface = sdf.Union(
        sdf.Translate(sdf.Rotate(sdf.Box((0.5, 0.4, 0.45), material=0), axis=(0.3, 1.0, 0.2),
                                 angle=20.0), offset=(-0.8, 0.0, 0.0)),
        sdf.Translate(sdf.Scale(sdf.Sphere(0.42, material=1), factor=1.3), offset=(0.8, 0.05, 0.0)),
        sdf.Plane(normal=(0.0, 1.0, 0.05), offset=-0.75, material=2),
    )
    materials = [
        Lambert((0.7, 0.5, 0.3)),
        CookTorrance(GGX(0.3), SchlickFresnel(0.5), diffuse=(0.2, 0.3, 0.4)),
        Phong(kd=(0.3, 0.4, 0.5), ks=0.5, q=3.0, normalized=True),
    ]
    lights = [jr.PointLight((1.5, 3.0, -2.5), (20.0, 18.0, 16.0)),
              jr.DirectionalLight((-0.4, 1.0, -0.6), (0.5, 0.6, 0.7))]
    scene = jr.Scene(surface, materials, lights, background=(0.1, 0.2, 0.3))
    camera = jr.PerspectiveCamera(eye=(0.1, 1.3, -3.0), target=(0.0, -0.1, 0.0), fov=45.0,
                                  width=24, height=18)
    return Problem(scene, camera, FD)


def test_placement_material_light_camera_gradients_match_finite_differences(placement_problem):
    p = placement_problem
    assert p.mask.sum() >= 80
    p.check([
        "half_extents", "axis", "angle", ".offset", "factor", "radius", "normal",       # shapes
        "albedo", "distribution.alpha", "f0", "diffuse", ".kd", ".ks", ".q",             # materials
        "position", "intensity", "direction", "irradiance",  # lights
        "eye", "target", "fov",  # camera
    ])


@pytest.fixture(scope="module")
def deformation_problem():
    surface = sdf.Union(
        sdf.Translate(sdf.SmoothUnion(sdf.Translate(sdf.Sphere(0.42, material=0), (-0.25, 0.0, 0.0)),
                                      sdf.Translate(sdf.Sphere(0.38, material=0), (0.3, 0.12, 0.0)),
                                      k=0.35), offset=(-1.15, 0.55, 0.0)),
        sdf.Translate(sdf.Twist(sdf.Box((0.35, 0.45, 0.35), material=1), rate=0.8, radius=0.5),
                      offset=(0.0, 0.55, 0.0)),
        sdf.Translate(sdf.Rotate(sdf.Bend(sdf.Box((0.5, 0.35, 0.3), material=2), rate=0.6,
                                          radius=0.65), axis=(1.0, 0.0, 0.0), angle=-60.0),
                      offset=(1.15, 0.55, 0.0)),
        sdf.Translate(sdf.Displace(sdf.Sphere(0.5, material=3), sdf.SineDisplacement(3.0),
                                   amplitude=0.04), offset=(-1.2, -0.6, 0.0)),
        sdf.Translate(sdf.Repeat(sdf.Sphere(0.36, material=4), period=(0.85, 0.0, 0.0),
                                 count=(1, 0, 0)), offset=(0.65, -0.6, 0.0)),
    )
    materials = [Lambert(c) for c in
                 [(0.7, 0.3, 0.3), (0.3, 0.7, 0.3), (0.3, 0.3, 0.7), (0.6, 0.6, 0.2), (0.2, 0.6, 0.6)]]
    scene = jr.Scene(surface, materials, [jr.PointLight((0.5, 2.0, -3.0), (25.0, 25.0, 25.0))],
                     background=0.05)
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, -3.3), target=(0.0, 0.0, 0.0), fov=42.0,
                                  width=36, height=24)
    return Problem(scene, camera, FD)


@pytest.mark.slow
def test_deformation_blend_and_repetition_gradients_match_finite_differences(deformation_problem):
    p = deformation_problem
    assert p.mask.sum() >= 60
    p.check([".child.k", "children_[1].child.rate", "children_[2].child.child.rate", "amplitude",
             "frequency", "period", "background"])


# -- depth 2: through mirrors and glass ----------------------------------------------


def _two_spheres_between_walls(materials):
    """Two spheres (materials 0 and 1) between a wall behind them (2) and one behind the
    camera (3), two point lights, at depth 2. Surfaces facing the camera within 30°:
    reflected rays then all reach the wall behind the camera and refracted ones the wall
    behind the spheres (no outline in the secondary images either)."""
    surface = sdf.Union(
        sdf.Translate(sdf.Sphere(0.8, material=0), offset=(-0.95, 0.0, 0.0)),
        sdf.Translate(sdf.Sphere(0.8, material=1), offset=(0.95, 0.0, 0.0)),
        sdf.Plane(normal=(0.0, 0.0, -1.0), offset=-3.0, material=2),   # wall behind, z = 3
        sdf.Plane(normal=(0.05, 0.0, 1.0), offset=-8.0, material=3),   # wall behind the camera
    )
    lights = [jr.PointLight((0.3, 2.5, -1.0), (30.0, 30.0, 30.0)),
              jr.PointLight((0.0, 1.0, 2.0), (10.0, 12.0, 14.0))]
    scene = jr.Scene(surface, materials, lights, background=0.0)
    camera = jr.PerspectiveCamera(eye=(0.0, 0.2, -3.2), target=(0.0, 0.0, 0.0), fov=40.0,
                                  width=32, height=20)
    return Problem(scene, camera, FD.replace(max_depth=2), facing=np.cos(np.radians(30.0)))


@pytest.fixture(scope="module")
def whitted_problem():
    return _two_spheres_between_walls(
        [Mirror((0.9, 0.8, 0.7)), Dielectric(1.5, absorption=(0.1, 0.2, 0.3)),
         Lambert((0.6, 0.5, 0.4)), Lambert((0.3, 0.5, 0.6))])


def test_gradients_through_reflection_and_refraction_at_depth_2(whitted_problem):
    p = whitted_problem
    # The window must include pixels on both spheres.
    assert p.mask[:, :16].sum() >= 8 and p.mask[:, 16:].sum() >= 8
    p.check(["tint", "eta", "absorption", "radius", ".offset", "albedo", "position",
             "intensity", "eye", "fov"])


@pytest.fixture(scope="module")
def specular_materials_problem():
    """The notes' Whitted material (a Phong base lit directly, constant c_refl/c_trans, η)
    and a smooth conductor (complex index η + iκ), between two walls, at depth 2."""
    return _two_spheres_between_walls(
        [Whitted(Phong(kd=(0.2, 0.3, 0.25), ks=0.4, q=6.0, normalized=True),
                 c_refl=(0.3, 0.25, 0.2), c_trans=(0.5, 0.55, 0.6), eta=1.4),
         Conductor(eta=(0.2, 0.4, 1.3), k=(3.6, 2.5, 1.9)),
         Lambert((0.6, 0.5, 0.4)), Lambert((0.3, 0.5, 0.6))])


@pytest.mark.slow
def test_whitted_and_conductor_parameters_through_reflection_and_refraction(
        specular_materials_problem):
    """c_refl, c_trans, η and the base's Phong exponent of `Whitted`; η and κ of
    `Conductor`; with the light and camera parameters, at depth 2."""
    p = specular_materials_problem
    assert p.mask[:, :16].sum() >= 8 and p.mask[:, 16:].sum() >= 8
    p.check(["c_refl", "c_trans", "materials[0].eta", "base.q", "materials[1].eta",
             "materials[1].k", "position", "intensity", "eye", "fov"])


@pytest.fixture(scope="module")
def dispersion_problem():
    """Two dispersive glass spheres (Cauchy and Sellmeier indices) in front of a lit wall,
    rendered spectrally (4 wavelength samples) at depth 2: the refracted rays of each
    wavelength bend by n(λ), so the image depends on every dispersion coefficient."""
    surface = sdf.Union(
        sdf.Translate(sdf.Sphere(0.8, material=0), offset=(-0.95, 0.0, 0.0)),
        sdf.Translate(sdf.Sphere(0.8, material=1), offset=(0.95, 0.0, 0.0)),
        sdf.Plane(normal=(0.0, 0.0, -1.0), offset=-3.0, material=2),
        sdf.Plane(normal=(0.05, 0.0, 1.0), offset=-8.0, material=3),
    )
    materials = [Dielectric(spectral.Cauchy(1.45, 0.02, 0.001)),
                 Dielectric(spectral.Sellmeier((1.04, 0.23, 1.01), (0.006, 0.02, 103.6))),
                 Lambert((0.6, 0.5, 0.4)), Lambert((0.3, 0.5, 0.6))]
    lights = [jr.PointLight((0.3, 2.5, -1.0), (30.0, 30.0, 30.0)),
              jr.PointLight((0.0, 1.0, 2.0), (10.0, 12.0, 14.0))]
    scene = jr.Scene(surface, materials, lights, background=0.0)
    camera = jr.PerspectiveCamera(eye=(0.0, 0.2, -3.2), target=(0.0, 0.0, 0.0), fov=40.0,
                                  width=24, height=14)
    return Problem(scene, camera, FD.replace(max_depth=2, wavelengths=4),
                   facing=np.cos(np.radians(30.0)))


@pytest.mark.slow
def test_dispersion_coefficients_get_gradients_through_refraction(dispersion_problem):
    """Cauchy a, b, c and Sellmeier B, C of dispersive dielectrics, in spectral mode."""
    p = dispersion_problem
    assert p.mask[:, :12].sum() >= 6 and p.mask[:, 12:].sum() >= 6
    p.check(["materials[0].eta.a", "materials[0].eta.b", "materials[0].eta.c",
             "materials[1].eta.b", "materials[1].eta.c"])


def _terrain_scene(height):
    """A height field under a sphere, lit by a point light, seen from above."""
    scene = jr.Scene(sdf.Translate(sdf.Sphere(0.4, material=1), (0.9, 0.6, 0.8)),
                     [Lambert((0.6, 0.5, 0.4)), Lambert((0.3, 0.5, 0.7))],
                     [jr.PointLight((0.5, 3.0, -1.0), (20.0, 20.0, 20.0))], background=0.2,
                     heightfields=[HeightField(height, material=0)])
    camera = jr.PerspectiveCamera(eye=(0.0, 2.0, -2.5), target=(0.0, 0.0, 0.5), fov=50.0,
                                  width=20, height=14)
    return scene, camera


@pytest.mark.parametrize("kind", ["sine", "grid"])
def test_height_field_parameters_match_finite_differences(kind):
    """Gradients through the height-field marcher's polished hit (its own implicit
    gradient, `jaxrt.heightfield`): a sine swell's amplitude, frequencies, phases and
    offset, and a bilinear grid's samples; with the light and camera."""
    if kind == "sine":
        height = SineHeight(0.15, frequency=(2.0, 1.3), phase=(0.3, 0.2), offset=-0.3)
        families = ["amplitude", "frequency", "phase", "height.offset"]
    else:
        rng = np.random.default_rng(3)
        height = GridHeight(-0.3 + 0.1 * rng.uniform(-1.0, 1.0, (3, 4)), extent=(-2.0, 2.0, -1.0, 3.0))
        families = ["heights"]
    p = Problem(*_terrain_scene(height), FD)
    assert p.mask.sum() >= 60
    p.check(families + ["position", "eye", "fov"])


# -- closed forms and invariances ----------------------------------------------------


def test_plane_moved_along_its_normal_moves_t_at_minus_one_over_cos():
    """t = (c − n·o) / (n·d) for the plane n·p = c: moving the plane along its normal by s
    moves the hit at dt/ds = 1 / (n·d) = −1 / cos θ, exactly, through a translation node
    and through the plane's offset, with both root solvers."""
    o = jnp.array([0.3, 2.0, -1.0])
    n = jnp.array([0.0, 1.0, 0.0])
    tilts = jnp.array([0.0, 0.4, 1.2, 2.5])
    d = jax.vmap(lambda a: jr.vecmath.normalize(jnp.array([jnp.sin(a), -1.0, 0.2])))(tilts)

    @jax.jit
    def rates(d):
        def translate(s, d):
            plane = sdf.Translate(sdf.Plane(normal=n, offset=0.0), offset=s * n)
            return jr.sphere_trace(plane, o, d, FD).t

        def offset(c, d):
            settings = FD.replace(root_solver="optimistix")
            return jr.sphere_trace(sdf.Plane(n, c), o, d, settings).t

        return (jax.vmap(jax.grad(translate), (None, 0))(0.0, d),
                jax.vmap(jax.grad(offset), (None, 0))(0.0, d))

    cos = -np.asarray(d @ n)
    for g in rates(d):
        np.testing.assert_allclose(np.asarray(g), -1.0 / cos, rtol=1e-12)


def _surface_fixed_scene(t):
    """Shapes whose surfaces do not move when θ moves along `SURFACE_FIXED_TANGENT`."""
    placed = lambda node, x: sdf.Translate(node, offset=(x, 0.0, 0.0))  # noqa: E731
    return sdf.Union(
        # a sphere rotated about its centre
        placed(sdf.Rotate(sdf.Sphere(0.45), axis=(0.2, 1.0, 0.3), angle=t[0]), -1.6),
        # a torus turned about its own axis
        placed(sdf.Rotate(sdf.Torus(0.4, 0.15), axis=(0.0, 1.0, 0.0), angle=t[1]), -0.55),
        # s·R constant: Scale(Sphere(R), s)
        placed(sdf.Scale(sdf.Sphere(t[2]), factor=t[3]), 0.55),
        # two translations with a constant sum
        sdf.Translate(sdf.Translate(sdf.Sphere(0.4), offset=t[4:7]), offset=t[7:10]),
        # a twist and a bend about the axes of a centred sphere
        placed(sdf.Bend(sdf.Twist(sdf.Sphere(0.4), rate=t[10], radius=0.5), rate=t[11],
                        radius=0.5), -1.0),
        # a box hidden inside a sphere
        placed(sdf.Union(sdf.Sphere(0.45), sdf.Translate(sdf.Box(t[12:15]), t[15:18])), 0.2),
        # a plane slid within itself
        sdf.Translate(sdf.Plane((0.0, 1.0, 0.0), -0.6), offset=t[18:21]),
    )


SURFACE_FIXED_THETA = [20.0, 15.0, 0.25, 1.6, 1.6, -0.6, 0.0, -0.1, 0.0, 0.1, 0.7, 0.4,
                       0.2, 0.2, 0.2, 0.1, 0.0, 0.0, 0.1, 0.0, 0.2]
SURFACE_FIXED_TANGENT = [1.0, 1.0, -0.25, 1.6, 1.0, -1.0, 0.5, -1.0, 1.0, -0.5, 1.0, 1.0,
                         1.0, 0.5, 0.2, 1.0, -1.0, 0.0, 1.0, 0.0, -0.5]


def _surface_fixed_image_tangent(silhouette):
    camera = jr.PerspectiveCamera(eye=(0.3, 1.2, -4.0), target=(0.0, 0.0, 0.0), fov=48.0,
                                  width=20, height=10)
    settings = FD.replace(silhouette=silhouette)
    light = [jr.PointLight((1.0, 3.0, -2.0), (20.0, 20.0, 20.0))]

    @jax.jit
    def tangent(theta, v):
        def image(t):
            scene = jr.Scene(_surface_fixed_scene(t), [Lambert(0.7)], light, background=0.2)
            return jr.render(scene, camera, settings).rgb
        return jax.jvp(image, (theta,), (v,))

    img, dimg = tangent(jnp.asarray(SURFACE_FIXED_THETA, jnp.float64),
                        jnp.asarray(SURFACE_FIXED_TANGENT, jnp.float64))
    assert np.ptp(np.asarray(img)) > 0.05  # the shapes are in view
    return float(np.max(np.abs(np.asarray(dimg))))


def test_shape_gradients_vanish_when_the_surface_is_held_fixed():
    """The derivative of the whole image along parameter directions that leave every
    surface unchanged (rotating a sphere about its centre, a torus about its axis,
    s·R fixed, two translations with a fixed sum, twisting and bending a centred sphere,
    moving a box hidden inside a sphere, sliding a plane within itself) is 0."""
    assert _surface_fixed_image_tangent(False) < 1e-9


@pytest.mark.slow
def test_shape_gradients_vanish_when_the_surface_is_held_fixed_with_silhouettes():
    """The same with the silhouette estimator on: outlines that do not move have no
    gradient either."""
    assert _surface_fixed_image_tangent(True) < 1e-9


def test_optimistix_and_hand_written_polish_agree_in_float64():
    """Values and gradients of the hit distance (w.r.t. every scene leaf and the ray) of
    the two root solvers agree to 1e-6 at newton_steps = 2, on rays that hit a sphere,
    a rotated box, a smooth blend with a twisted box and a displaced torus."""
    shape = sdf.Union(
        sdf.Translate(sdf.Sphere(0.5), (-1.2, 0.6, 0.0)),
        sdf.Translate(sdf.Rotate(sdf.Box((0.4, 0.35, 0.3)), axis=(1.0, 1.0, 0.0), angle=25.0),
                      offset=(0.0, 0.6, 0.2)),
        sdf.Translate(sdf.SmoothUnion(sdf.Translate(sdf.Sphere(0.35), (0.25, 0.0, 0.0)),
                                      sdf.Twist(sdf.Box((0.25, 0.45, 0.25)), 0.7), k=0.2),
                      offset=(1.2, 0.6, 0.0)),
        sdf.Translate(sdf.Displace(sdf.Torus(0.5, 0.2), sdf.SineDisplacement(3.0), amplitude=0.03),
                      offset=(0.0, -0.6, 0.0)),
    )
    rng = np.random.default_rng(1)
    targets = np.array([[-1.2, 0.6, 0.0], [0.0, 0.6, 0.0], [1.2, 0.6, 0.0], [0.5, -0.6, 0.0]])
    targets = np.repeat(targets, 4, axis=0) + rng.uniform(-0.12, 0.12, (16, 3))
    origins = np.tile([0.0, 0.0, -4.0], (16, 1))
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    base = jr.RenderSettings(dtype="float64", newton_steps=2)

    @eqx.filter_jit
    def value_grad(shape, o, d, solver):
        settings = base.replace(root_solver=solver)
        f = lambda shape, o, d: jr.sphere_trace(shape, o, d, settings).t  # noqa: E731

        def one(o, d):
            return (f(shape, o, d), jax.grad(lambda s: f(s, o, d))(shape),
                    jax.grad(f, argnums=(1, 2))(shape, o, d))
        return jax.vmap(one)(o, d)

    o, d = jnp.asarray(origins), jnp.asarray(directions)
    hits = jax.vmap(lambda o, d: jr.sphere_trace(shape, o, d, base).hit)(o, d)
    assert int(hits.sum()) >= 14
    a = value_grad(shape, o, d, "newton")
    b = value_grad(shape, o, d, "optimistix")
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        assert np.allclose(x, y, rtol=1e-6, atol=1e-6 * max(1.0, np.max(np.abs(x))))
    # Gradients with respect to the scene are not all 0 (the test compares something).
    assert max(float(np.max(np.abs(np.asarray(x)))) for x in jax.tree_util.tree_leaves(a[1])) > 0.1


def test_gradient_memory_and_program_do_not_grow_with_max_steps():
    """The gradient program of a render is the same size at max_steps 64 and 1024 (the
    march is a loop with a static bound, not unrolled, and not differentiated) and
    needs the same temporary memory (XLA's memory analysis) within 10 %."""
    scene = jr.Scene(sdf.Translate(sdf.Sphere(1.0), (0.0, 0.2, 0.0)), [Lambert(0.7)],
                     [jr.PointLight((1.0, 3.0, -2.0), (20.0, 20.0, 20.0))])
    camera = jr.PerspectiveCamera(width=8, height=8)

    def measure(max_steps):
        settings = jr.RenderSettings(max_steps=max_steps, shadow_steps=max_steps)
        grad = jax.grad(lambda s: jnp.mean(jr.render(s, camera, settings).rgb))
        radius = jnp.asarray(1.0, jnp.float32)
        f = lambda r: grad(eqx.tree_at(lambda s: s.surface.child.radius, scene, r))  # noqa: E731
        jaxpr = jax.make_jaxpr(f)(radius)
        compiled = jax.jit(f).lower(radius).compile()
        memory = compiled.memory_analysis()
        temp = None if memory is None else memory.temp_size_in_bytes
        return len(str(jaxpr)), temp

    size64, temp64 = measure(64)
    size1024, temp1024 = measure(1024)
    assert abs(size1024 - size64) <= 16  # only the printed constant differs
    if temp64 is not None:
        assert abs(temp1024 - temp64) <= 0.1 * max(temp64, 1)


# -- the extremes: finite values and gradients with jax_debug_nans ---------------------


@pytest.fixture
def debug_nans():
    jax.config.update("jax_debug_nans", True)
    yield
    jax.config.update("jax_debug_nans", False)


def _finite(tree):
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree)
               if eqx.is_array(x))


def test_sphere_trace_gradients_are_finite_at_the_extremes(debug_nans):
    """Tangent rays, rays from on and inside the surface and from its centre, a miss,
    an exhausted budget; and every primitive's gradient at its own centre."""
    z = [0.0, 0.0, 1.0]
    cases = {"tangent": [1.0, 0.0, -3.0], "on the surface": [0.0, 0.0, -1.0],
             "inside": [0.0, 0.3, 0.0], "at the centre": [0.0, 0.0, 0.0],
             "missing": [3.0, 0.0, -3.0], "far": [0.0, 0.0, -50.0]}
    origins = jnp.asarray(list(cases.values()))
    directions = jnp.asarray([z] * len(cases))

    @eqx.filter_jit
    def grads(shape, o, d, settings):
        f = lambda shape, o, d: jr.sphere_trace(shape, o, d, settings).t  # noqa: E731
        return jax.vmap(lambda o, d: (jax.grad(lambda s: f(s, o, d))(shape),
                                      jax.grad(f, argnums=(1, 2))(shape, o, d)))(o, d)

    sphere = sdf.Translate(sdf.Sphere(1.0), (0.0, 0.0, 0.0))
    settings = jr.RenderSettings(dtype="float64")
    assert _finite(grads(sphere, origins, directions, settings))
    assert _finite(grads(sphere, origins, directions, settings.replace(max_steps=2)))
    for shape in (sdf.Sphere(0.5), sdf.Box((0.5, 0.5, 0.5)), sdf.Torus(0.6, 0.2),
                  sdf.Cylinder(0.4, 0.5), sdf.Capsule(0.5, 0.2), sdf.Cone(0.5, 1.0),
                  sdf.Ellipsoid((0.5, 0.3, 0.4)), sdf.RoundBox((0.5, 0.4, 0.3), 0.1)):
        g = eqx.filter_grad(lambda s, p: s(p), )(shape, jnp.zeros(3))
        assert _finite(g) and _finite(jax.grad(lambda p: shape(p))(jnp.zeros(3))), shape


@pytest.fixture(scope="module")
def extreme_scene():
    """Spheres of glass (η = 1.5: total internal reflection and critical angles at their
    rims), of η = 1 (no interface), of a GGX conductor-like gloss with roughness 1e-4,
    and a Lambert one, on a floor, under a point light."""
    surface = sdf.Union(
        sdf.Translate(sdf.Sphere(0.5, material=0), (-1.5, 0.0, 0.0)),
        sdf.Translate(sdf.Sphere(0.5, material=1), (-0.5, 0.0, 0.0)),
        sdf.Translate(sdf.Sphere(0.5, material=2), (0.5, 0.0, 0.0)),
        sdf.Translate(sdf.Sphere(0.5, material=3), (1.5, 0.0, 0.0)),
        sdf.Plane((0.0, 1.0, 0.0), -0.5, material=3),
    )
    materials = [Dielectric(1.5), Dielectric(1.0), CookTorrance(GGX(1e-4), SchlickFresnel(0.9)),
                 Lambert(0.6)]
    return jr.Scene(surface, materials, [jr.PointLight((1.0, 3.0, -2.0), (20.0, 20.0, 20.0))],
                    background=0.1)


def _extreme_render(scene, where, settings):
    eye, target = (((0.0, 0.6, -4.0), (0.0, 0.0, 0.0)) if where == "outside"
                   else ((-1.5, 0.0, 0.0), (-1.5, 0.0, 1.0)))
    camera = jr.PerspectiveCamera(eye=eye, target=target, fov=60.0, width=12, height=6)
    value, grads = _render_value_and_grad(scene, camera, settings)
    assert np.isfinite(float(value)) and _finite(grads)


@pytest.mark.parametrize("where", ["outside", "inside"])
def test_render_gradients_are_finite_at_the_extremes(extreme_scene, where, debug_nans):
    """With shadows and one level of reflection and refraction, from a camera outside and
    one at the centre of the glass sphere (rays that start inside a surface)."""
    _extreme_render(extreme_scene, where, jr.RenderSettings(dtype="float64", max_depth=1))


@pytest.mark.slow
@pytest.mark.parametrize("where", ["outside", "inside"])
def test_render_gradients_are_finite_at_the_extremes_with_silhouettes(extreme_scene, where,
                                                                      debug_nans):
    """The same at depth 2 with the silhouette estimator on."""
    _extreme_render(extreme_scene, where,
                    jr.RenderSettings(dtype="float64", max_depth=2, silhouette=True))


@eqx.filter_jit
def _render_value_and_grad(scene, camera, settings):
    loss = lambda sc, cam: jnp.mean(jr.render(sc, cam, settings).rgb)  # noqa: E731
    return eqx.filter_value_and_grad(lambda args: loss(*args))((scene, camera))


def test_refraction_at_exactly_the_critical_angle_has_finite_gradients(debug_nans):
    """A ray inside glass (η = 1.5) meets a flat interface at exactly θc = asin(1/η)."""
    from jaxrt.integrator import trace_radiance

    eta = 1.5
    theta = np.arcsin(1.0 / eta)
    glass = sdf.Plane((0.0, 1.0, 0.0), 0.0, material=0)   # glass below y = 0
    ceiling = sdf.Plane((0.0, -1.0, 0.0), -2.0, material=1)  # a ceiling at y = 2
    scene = jr.Scene(sdf.Union(glass, ceiling), [Dielectric(eta), Lambert(0.5)],
                     [jr.PointLight((0.0, 1.0, 0.0), (5.0, 5.0, 5.0))], background=0.2)
    settings = jr.RenderSettings(dtype="float64", max_depth=1)
    origin = jnp.array([0.0, -1.0, 0.0])
    direction = jnp.array([np.sin(theta), np.cos(theta), 0.0])

    @eqx.filter_jit
    def value_and_grads(scene, origin, direction):
        def radiance(scene, origin, direction):
            return jnp.sum(trace_radiance(scene, origin, direction, jnp.zeros(2), settings)["rgb"])
        return (radiance(scene, origin, direction),
                jax.grad(radiance, argnums=(0, 1, 2))(scene, origin, direction))

    value, grads = value_and_grads(scene, origin, direction)
    assert np.isfinite(float(value)) and _finite(grads)


def _tiny_scene(scale):
    s = scale
    surface = sdf.Union(sdf.Translate(sdf.Sphere(0.8 * s, material=0), (0.0, 0.0, 0.0)),
                        sdf.Plane((0.0, 1.0, 0.0), -0.8 * s, material=1))
    scene = jr.Scene(surface, [Lambert(0.6), Lambert(0.5)],
                     [jr.PointLight((s, 3.0 * s, -2.0 * s), (20.0 * s * s,) * 3)], background=0.1)
    camera = jr.PerspectiveCamera(eye=(0.0, 0.5 * s, -3.5 * s), target=(0.0, 0.0, 0.0), fov=45.0,
                                  width=6, height=5)
    return scene, camera


def test_gradients_are_finite_and_scale_with_the_scene(debug_nans):
    """Scaling the scene by s (lengths; light intensity by s², so that irradiance is
    unchanged; epsilons with the scene) leaves the image unchanged and divides the
    radius gradient by s: the scenes at s = 1e-3 and 1e3 agree; everything is finite."""

    def value_grad(scale):
        scene, camera = _tiny_scene(scale)
        settings = FD.replace(shadows="hard", hit_epsilon=1e-7 * scale, max_distance=100.0 * scale)
        value, grads = _render_value_and_grad(scene, camera, settings)
        assert np.isfinite(float(value)) and _finite(grads), scale
        return float(value), float(grads[0].surface.children_[0].child.radius)

    v_small, g_small = value_grad(1e-3)
    v_large, g_large = value_grad(1e3)
    assert v_small == pytest.approx(v_large, rel=1e-6)
    assert g_small * 1e-3 == pytest.approx(g_large * 1e3, rel=1e-5)


# -- record and replay: the fast backends' gradients ---------------------------------


def _replay_scene(dispersive=False):
    """A mirror and a glass sphere over a sine height field and a wall, soft shadows from
    a point light: every kind of march (camera, reflected, refracted, soft shadow,
    height field, height-field shadow) in one small image."""
    surface = sdf.Union(
        sdf.Translate(sdf.Sphere(0.7, material=0), offset=(-0.8, 0.1, 0.0)),
        sdf.Translate(sdf.Sphere(0.6, material=1), offset=(0.8, 0.0, 0.2)),
        sdf.Plane(normal=(0.0, 0.0, -1.0), offset=-3.0, material=2),
    )
    glass = Dielectric(spectral.Cauchy(1.45, 0.02, 0.001)) if dispersive else Dielectric(1.5, absorption=(0.1, 0.2, 0.3))
    materials = [Mirror((0.9, 0.8, 0.7)), glass, Lambert((0.6, 0.5, 0.4)), Lambert((0.3, 0.5, 0.6))]
    field = HeightField(SineHeight(0.1, frequency=(2.0, 1.3), phase=(0.3, 0.2), offset=-0.7), material=3)
    scene = jr.Scene(surface, materials, [jr.PointLight((0.5, 3.0, -1.5), (25.0, 25.0, 25.0))],
                     background=(0.1, 0.2, 0.3), heightfields=[field])
    camera = jr.PerspectiveCamera(eye=(0.0, 0.8, -3.5), target=(0.0, 0.0, 0.0), fov=50.0,
                                  width=10, height=6)
    settings = jr.RenderSettings(dtype="float64", max_depth=1, shadows="soft", batch_size=64)
    return scene, camera, settings


REPLAY_VARIANTS = {
    "whitted": {},  # the default tree: a scan on a CPU
    "unrolled": dict(recursion="unrolled"),
    "silhouette": dict(silhouette=True, max_depth=0),
    # 15 slots: the lane kernel skips those dead in a tile of 16 rays, and the replay
    # shades a slot in batches of 16 of the 60 rays, only those with a ray alive in it
    "scan": dict(recursion="scan", max_depth=3, batch_size=16,
                 kernel=jr.KernelOptions(replay_gather=16)),
    "float32": dict(dtype="float32"),
}


@pytest.mark.parametrize("variant", ["whitted"] + [pytest.param(v, marks=pytest.mark.slow)
                                                   for v in REPLAY_VARIANTS if v != "whitted"])
def test_replay_image_equals_the_record(variant):
    """The loop-free replay of a recorded render (every march read from the tape) computes
    the lane kernel's image and AOVs, to rounding."""
    from jaxrt.render import replay_image

    scene, camera, settings = _replay_scene()
    settings = settings.replace(backend="fused", **REPLAY_VARIANTS[variant])
    record, replay = replay_image(scene, camera, settings)
    tol = 1e-5 if settings.dtype == "float32" else 1e-12
    assert float(np.ptp(np.asarray(record["rgb"]))) > 0.1
    for name in record:
        a, b = np.asarray(record[name]), np.asarray(replay[name])
        assert np.max(np.abs(a - b)) <= tol * max(1.0, np.max(np.abs(a))), name


@pytest.mark.parametrize("recursion", ["scan", pytest.param("unrolled", marks=pytest.mark.slow)])
def test_replay_shades_only_the_live_rays_of_the_tree(recursion):
    """On "fused", the replay shades the secondary rays of the ray tree (a level, or a
    slot of the scan tree) only in the batches of rays that hold a live one
    (`tape._gathered`; its program: tests/test_tape.py), where without gathering
    (`replay_gather = 0`) every ray of the tree is shaded for every pixel: the
    gradients are the same (float64; the values: test_replay_image_equals_the_record)."""
    from jaxrt.render import _replay_gathers

    scene, camera, settings = _replay_scene()
    scene = jr.Scene(scene.surface, scene.materials[:3], scene.lights, background=scene.background)
    settings = settings.replace(backend="fused", recursion=recursion, shadows="none")  # 3 rays
    plain = settings.replace(kernel=jr.KernelOptions(replay_gather=0))
    gathered = settings.replace(kernel=jr.KernelOptions(replay_gather=16))
    assert _replay_gathers(gathered, scene) == 16 and _replay_gathers(plain, scene) == 0
    assert _replay_gathers(gathered.replace(max_depth=0), scene) == 0
    assert _replay_gathers(gathered.replace(backend="jax"), scene) == 0

    grads = {}
    for name, s in (("plain", plain), ("gathered", gathered)):
        loss = lambda p, s=s: jnp.sum(jr.render(*p, s).rgb * jnp.linspace(0.5, 1.5, 3))  # noqa: E731
        value, grad = eqx.filter_value_and_grad(loss)((scene, camera))
        grads[name] = (float(value), ravel_pytree(eqx.filter(grad, eqx.is_inexact_array))[0])
    assert grads["gathered"][0] == pytest.approx(grads["plain"][0], rel=1e-12)
    a, b = np.asarray(grads["gathered"][1]), np.asarray(grads["plain"][1])
    assert np.max(np.abs(b)) > 0
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.max(np.abs(b)))


@pytest.mark.parametrize("variant, backend", [
    ("no-heightfield", "fused"),
    pytest.param("whitted", "fused", marks=pytest.mark.slow),
    pytest.param("silhouette", "fused", marks=pytest.mark.slow),
    pytest.param("scan", "fused", marks=pytest.mark.slow),
    pytest.param("whitted", "pallas", marks=pytest.mark.slow),  # interpreted on a CPU
])
def test_replay_differentiated_in_a_lane_kernel_has_the_same_gradient(variant, backend):
    """`KernelOptions.replay_kernel`: each sample's VJP of its replay, run by the lane
    kernel and summed over its tiles, is the VJP of the vmapped replay: the same value
    and gradient (float64; mirror, glass, soft shadows, a height field, silhouettes,
    a scanned tree with dead slots). Tiles of 4×4 samples over the 10×6 image: its sums
    leave the padding's samples out. The quick variant leaves the height field out (its
    march and shadow make the kernel's VJP half as large again: 76 s of the quick suite
    with it, on 2 cores); "whitted" (slow) has it."""
    scene, camera, settings = _replay_scene()
    if variant == "no-heightfield":
        scene, variant = jr.Scene(scene.surface, scene.materials, scene.lights,
                                  background=scene.background), "whitted"
    settings = settings.replace(backend=backend, **{"batch_size": 16, **REPLAY_VARIANTS[variant]})
    weights = jnp.linspace(0.5, 1.5, 3)
    dyn, static = eqx.partition((scene, camera), eqx.is_inexact_array)
    grads = {}
    for in_kernel in (False, True):
        s = settings.replace(kernel=settings.kernel.replace(replay_kernel=in_kernel))

        def loss(d, s=s):
            return jnp.sum(jr.render(*eqx.combine(d, static), s).rgb * weights)

        value, grad = jax.value_and_grad(loss)(dyn)
        grads[in_kernel] = (float(value), np.asarray(ravel_pytree(grad)[0]))
    assert grads[True][0] == pytest.approx(grads[False][0], rel=1e-12)
    a, b = grads[True][1], grads[False][1]
    assert np.max(np.abs(b)) > 0
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.max(np.abs(b)))


def test_replay_kernel_by_default_only_for_small_vjp_programs():
    """`replay_kernel = None` runs the replay's VJP in a Pallas kernel when its program is
    at most `replay_kernel_max_lane_ops`, else XLA's reverse pass, with no warning: a
    gradient is the recording Pallas kernel and one for the VJP, or the first alone.
    Off on "fused". (The replay scene without its mirror, glass and height field, at
    depth 0 with hard shadows: the choice depends on the program's size only, and
    tracing the whole scene for Pallas three times took 22 s.)"""
    scene, camera, settings = _replay_scene()
    scene = jr.Scene(scene.surface, [Lambert((0.6, 0.5, 0.4))] * 4, scene.lights,
                     background=scene.background)
    settings = settings.replace(max_depth=0, shadows="hard")
    dyn, static = eqx.partition((scene, camera), eqx.is_inexact_array)

    def kernels(backend, limit):
        s = settings.replace(backend=backend, kernel=jr.KernelOptions(
            replay_kernel_max_lane_ops=limit, interpret=True))
        grad = jax.grad(lambda d: jnp.sum(jr.render(*eqx.combine(d, static), s).rgb))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            return str(jax.make_jaxpr(grad)(dyn)).count("pallas_call[")

    assert kernels("pallas", 10**6) == 2
    assert kernels("pallas", 1) == 1
    assert kernels("fused", 10**6) == 0


def _lane_call_outputs(jaxpr):
    """The number of outputs of each outermost `custom_vjp_call` in `jaxpr` (the lane
    kernel of `jaxrt.kernels.fused.map_samples`), nested jaxprs included."""
    counts = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name.startswith("custom_vjp_call"):
            counts.append(len(eqn.outvars))
            continue
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else [value]:
                if hasattr(sub, "eqns"):
                    counts += _lane_call_outputs(sub)
                elif hasattr(sub, "jaxpr") and hasattr(sub.jaxpr, "eqns"):
                    counts += _lane_call_outputs(sub.jaxpr)
    return counts


def test_plain_render_writes_no_tape_and_equals_the_recorded_image():
    """A render with no derivative runs the lane kernel alone (its outputs are the image
    and AOVs, no tape); a derivative runs the recording kernel, whose image is the plain
    kernel's to rounding (float64; mirror, glass, soft shadows, a height field)."""
    from jaxrt.render import replay_image

    scene, camera, settings = _replay_scene()
    settings = settings.replace(backend="fused")
    n_outputs = 1 + len(settings.aovs)
    loss = lambda p: jnp.sum(jr.render(*p, settings).rgb)  # noqa: E731
    plain = jax.make_jaxpr(loss)((scene, camera)).jaxpr
    assert _lane_call_outputs(plain) == [n_outputs]
    for derivative in (eqx.filter_value_and_grad(loss),
                       lambda p: eqx.filter_jvp(loss, (p,), (p,))):
        calls = _lane_call_outputs(jax.make_jaxpr(derivative)((scene, camera)).jaxpr)
        assert len(calls) == 1 and calls[0] > n_outputs  # the image and its tape

    image = jr.render(scene, camera, settings)
    record, _ = replay_image(scene, camera, settings)
    assert float(np.ptp(np.asarray(image.rgb))) > 0.1
    for name in record:
        a = np.asarray(getattr(image, name))
        b = np.asarray(record[name]).reshape(a.shape)
        assert np.max(np.abs(a - b)) <= 1e-12 * max(1.0, np.max(np.abs(b))), name


@pytest.mark.slow
@pytest.mark.parametrize("recursion", ["unrolled", "scan"])
def test_replay_gradients_equal_the_reference_path_on_every_march(recursion):
    """Mirror, glass, soft shadows (now differentiable), a height field and its shadows:
    the record/replay gradient of every scene and camera float equals the "jax" path's.
    With the ray tree as a scan (3 levels: 15 slots, most dead for every ray), "fused"
    skips the slots dead for a whole tile of 16 rays, whose records are zeros, and the
    replay shades each slot only in the batches of rays alive in it (`tape._gathered`)."""
    scene, camera, settings = _replay_scene()
    settings = settings.replace(backend="jax", recursion=recursion)
    if recursion == "scan":
        settings = settings.replace(max_depth=3, batch_size=16,
                                    kernel=jr.KernelOptions(replay_gather=16))
    Problem(scene, camera, settings, erode=0).check_replay("fused")


@pytest.mark.slow
@pytest.mark.parametrize("problem", ["whitted_problem", "placement_problem", "specular_materials_problem",
                                     "dispersion_problem", "deformation_problem"])
def test_replay_gradients_equal_the_reference_path(problem, request):
    """The existing gradient problems (shapes, placements, materials, lights, camera;
    mirrors, glass, η, absorption; Whitted and conductor parameters; dispersion in
    spectral mode, which "auto" records with the vmapped program; deformations)."""
    request.getfixturevalue(problem).check_replay()


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["sine", "grid"])
def test_replay_gradients_equal_the_reference_path_through_height_fields(kind):
    if kind == "sine":
        height = SineHeight(0.15, frequency=(2.0, 1.3), phase=(0.3, 0.2), offset=-0.3)
    else:
        rng = np.random.default_rng(3)
        height = GridHeight(-0.3 + 0.1 * rng.uniform(-1.0, 1.0, (3, 4)), extent=(-2.0, 2.0, -1.0, 3.0))
    Problem(*_terrain_scene(height), FD).check_replay()


@pytest.mark.slow
def test_replay_gradients_equal_the_reference_path_with_silhouettes():
    """Outline gradients (the silhouette estimator: near-miss search, projection, inner
    ray) over every pixel, outlines included."""
    scene, camera, settings = _replay_scene()
    settings = settings.replace(backend="jax", silhouette=True, max_depth=0, shadows="hard")
    Problem(scene, camera, settings, erode=0).check_replay("fused")


# -- soft shadows: the penumbra's gradient (envelope theorem) ------------------------


def _penumbra_scene(x):
    """A sphere (centre x[:3], radius x[3]) over a floor, a point light at x[4:7]."""
    surface = sdf.Union(sdf.Translate(sdf.Sphere(x[3], material=0), offset=x[:3]),
                        sdf.Plane((0.0, 1.0, 0.0), 0.0, material=1))
    return jr.Scene(surface, [Lambert(0.7), Lambert(0.6)],
                    [jr.PointLight(x[4:7], (30.0, 30.0, 30.0))], background=0.0)


PENUMBRA_X0 = np.array([0.0, 0.8, 0.5, 0.5, 0.5, 3.0, -0.5])


def test_soft_shadow_penumbra_gradient_matches_finite_differences():
    """The soft shadow of a sphere on a floor, seen from above, as the sphere moves and
    grows and the light moves: the gradient of a weighted sum of the floor's pixels
    (penumbra, umbra and lit parts; no outline) against float64 central differences.
    Visibility is smoothstep(k·f/t) at the march's refined minimiser t*, held fixed
    (envelope theorem); it used to have no gradient at all."""
    from scipy.ndimage import binary_erosion

    camera = jr.PerspectiveCamera(eye=(0.0, 4.0, -2.0), target=(0.0, 0.0, 0.3), fov=50.0,
                                  width=20, height=14)
    settings = FD.replace(shadows="soft", shadow_steps=64, penumbra=4.0)
    image = jr.render(_penumbra_scene(jnp.asarray(PENUMBRA_X0)), camera, settings)
    floor = binary_erosion(np.abs(np.asarray(image.albedo)[..., 0] - 0.6) < 1e-9)
    shade = np.asarray(image.rgb)[..., 0][floor]
    assert floor.sum() >= 100 and shade.min() < 0.2 * shade.max()  # the shadow is in view
    weights = jnp.asarray(floor * np.random.default_rng(0).uniform(0.5, 1.5, floor.shape))
    loss = jax.jit(lambda x: jnp.sum(jr.render(_penumbra_scene(x), camera, settings).rgb[..., 0]
                                     * weights))
    g = np.asarray(jax.grad(loss)(jnp.asarray(PENUMBRA_X0)))
    h = 1e-5
    fd = np.array([(float(loss(PENUMBRA_X0 + h * e)) - float(loss(PENUMBRA_X0 - h * e))) / (2 * h)
                   for e in np.eye(len(PENUMBRA_X0))])
    # measured: 0.25 % (norm), 0.7 % worst component; 1.8 % / 4.6 % at the sampled
    # minimum without the golden-section refinement
    assert np.linalg.norm(g - fd) <= 0.01 * np.linalg.norm(fd)
    np.testing.assert_allclose(g, fd, rtol=0.02, atol=0.01 * np.max(np.abs(fd)))
