"""Each march site holds the scene SDF as few times as its computation needs (issue 12).

A counting wrapper around the scene's surface counts, at trace time, how often each
site of the traced program evaluates it (`value_and_grad` and `grad` trace it once):
that is the number of copies of the scene's code in the compiled program. Loops with a
static bound (Newton polish, origin settling, golden section) are loops, so the counts
do not depend on newton_steps, spawn_steps, refine_steps or the step budgets. That is
the "phases" form of the marches (`jaxrt.march.form`, the default); the "plain" form
(the Pallas kernel's) holds a fixed few copies per march instead (the last test).
"""

import collections
import traceback

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import integrator, lights
from jaxrt.march import form, shadow, sphere
from jaxrt.sdf.base import SDF


#: Frames that do not name a site: calls, loop bodies, the JVP rule of `trace.evaluated`.
_PLUMBING = ("__call__", "<lambda>", "step", "repeat", "body", "apply", "known_jvp", "evaluated",
             "value_and_gradient", "f_and_grad")


class Counting(SDF):
    """`child`, counting its evaluations by the jaxrt function that asked for them."""

    child: SDF
    calls: collections.Counter = eqx.field(static=True)

    def __init__(self, child, calls):
        self.child = child
        self.calls = calls

    def eval(self, p):
        site = next(f.name for f in reversed(traceback.extract_stack()[:-1])
                    if "jaxrt" in f.filename and "/sdf/" not in f.filename
                    and f.name not in _PLUMBING)
        self.calls[site] += 1
        return self.child.eval(p)

    def lipschitz(self):
        return self.child.lipschitz()

    def children(self):
        return (self.child,)


def _scene(calls):
    surface = jr.sdf.Union(jr.sdf.Sphere(radius=1.0, material=0),
                           jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=-1.0, material=1))
    return jr.Scene(surface=Counting(surface, calls),
                    materials=[jr.bsdf.Lambert(0.8), jr.bsdf.Lambert(0.5)],
                    lights=[jr.PointLight((1.0, 4.0, -2.0), (10.0, 10.0, 10.0))])


def _counts(settings, fn=None):
    """{site: evaluations} of one camera ray's `trace_radiance` (or of `fn(scene)`)."""
    calls = collections.Counter()
    scene = _scene(calls)
    o, d, cone = jnp.array([0.0, 1.0, -5.0]), jnp.array([0.0, 0.0, 1.0]), jnp.zeros(2)
    if fn is None:
        fn = lambda s: integrator.trace_radiance(s, o, d, cone, settings)["rgb"]  # noqa: E731
    jax.make_jaxpr(fn)(scene)
    return dict(calls)


@pytest.mark.parametrize("shadows", ["soft", "hard"])
def test_each_site_evaluates_the_scene_once_whatever_the_step_counts(shadows):
    """A diffuse scene with one light: the camera march (1), the Newton polish's loop
    (f and ∇f, 1, which also gives the normal and material at the hit), the origin
    settling (1) and the shadow march (1), for every newton_steps ≥ 1 and
    spawn_steps ≥ 1. The last Newton step, the normal and the penumbra take their values
    from the marches: only a derivative adds their evaluation (`trace.evaluated`), one
    each."""
    # "march": the camera ray's and the shadow ray's (sphere-traced, unpolished, if hard).
    expected = {"march": 2, "newton_march": 1, "surface_distance": 1}
    # A derivative adds the last Newton step's, the normal's and the penumbra's (the
    # latter is traced when the light scan is differentiated, so it is counted there,
    # not by name).
    added = 3 if shadows == "soft" else 2
    o, d, cone = jnp.array([0.0, 1.0, -5.0]), jnp.array([0.0, 0.0, 1.0]), jnp.zeros(2)
    for newton, spawn, budget in ((1, 1, 8), (2, 2, 128), (5, 4, 300)):
        settings = jr.RenderSettings(shadows=shadows, newton_steps=newton, spawn_steps=spawn,
                                     max_steps=budget, shadow_steps=budget)
        assert _counts(settings) == expected, (newton, spawn)

        def loss(scene):
            rgb = lambda s: integrator.trace_radiance(s, o, d, cone, settings)["rgb"]  # noqa: E731
            return eqx.filter_grad(lambda s: jnp.sum(rgb(s)))(scene)

        counts = _counts(settings, loss)
        assert counts["newton_at"] == 1 and counts["unit_gradient"] == 1
        assert sum(counts.values()) == sum(expected.values()) + added, counts
        assert all(counts[site] >= n for site, n in expected.items()), counts


@pytest.mark.parametrize("refine", [0, 3, 8])
def test_soft_shadow_march_evaluates_the_scene_once(refine):
    """The sign at the origin, the march, the end sample of a ray out of budget and the
    golden-section refinement share one evaluation (phases of one loop)."""
    options = shadow.SoftShadow(max_steps=16, refine_steps=refine)
    o, wi = jnp.array([0.0, -0.5, -3.0]), jnp.array([0.0, 1.0, 0.0])

    def fn(scene):
        return shadow.march(scene.surface, o, wi, jnp.asarray(5.0), options)["t"]

    assert _counts(None, fn) == {"march": 1}


@pytest.mark.parametrize("relax", [1.0, 1.6])
def test_sphere_march_evaluates_the_scene_once(relax):
    """f(o), the march and the secant finish share one evaluation."""
    options = sphere.SphereTracing(max_steps=4, over_relaxation=relax)
    o, d = jnp.array([0.0, 1.0, -5.0]), jnp.array([0.0, 0.0, 1.0])

    def fn(scene):
        return sphere.march(scene.surface, o, d, options, jnp.zeros(2), 100.0)["t"]

    assert _counts(None, fn) == {"march": 1}


def test_penumbra_reads_the_sign_of_the_march():
    """`lights.penumbra` does not evaluate the scene in a render without derivatives:
    the side of the surface the ray starts on and f at the minimum are the march's."""
    settings = jr.RenderSettings(shadows="soft")
    o, wi = jnp.array([0.0, -0.5, -3.0]), jnp.array([0.0, 1.0, 0.0])

    def fn(scene):
        return lights.shadow_ray(scene.surface, o, wi, jnp.asarray(5.0), settings)

    assert _counts(None, fn) == {"march": 1}


def test_silhouette_sites_evaluate_the_scene_once_each():
    """The silhouette estimator's searches (golden section with h(t_c), the projection,
    the regula falsi with its bracket ends) and f, ∇f, H at the near miss are one copy
    each; its counts do not depend on newton_steps or spawn_steps."""
    counts = []
    for newton, spawn in ((1, 1), (3, 3)):
        settings = jr.RenderSettings(silhouette=True, max_depth=0, newton_steps=newton,
                                     spawn_steps=spawn)
        camera = jr.PerspectiveCamera(eye=(0.0, 1.0, -5.0), target=(0.0, 0.0, 0.0),
                                      up=(0.0, 1.0, 0.0), fov=40.0, width=8, height=6)
        from jaxrt import silhouette

        def fn(scene):
            o, d, cone = camera.generate_ray(4.0, 3.0)
            out = integrator.trace_radiance(scene, o, d, cone, settings)
            return silhouette.blend(scene, camera, jnp.array([4.0, 3.0]), out, settings)["rgb"]

        counts.append(_counts(settings, fn))
    assert counts[0] == counts[1]
    for site in ("h", "value_and_grad", "project_to_surface", "coverage", "g"):
        assert counts[0][site] == 1, (site, counts[0])


def test_plain_form_holds_a_fixed_few_copies_per_march():
    """The "plain" form: the sphere march and the soft-shadow march hold f three times
    each (f(o), the loop's step, the finish: the secant point, the sample after the
    last), the shadow's golden section three (x1, x2, the loop's step), whatever the
    budgets; loops of at most `form.PLAIN_UNROLL` iterations are straight code (the
    Newton polish holds newton_steps copies, the settling spawn_steps), longer ones stay
    loops (one copy); the normal is an evaluation of its own (unrolled, a last Newton
    iteration for it made the Warp scene's Pallas render slower)."""
    o, wi = jnp.array([0.0, -0.5, -3.0]), jnp.array([0.0, 1.0, 0.0])
    with form.using("plain"):
        for budget in (4, 64):
            for relax in (1.0, 1.6):
                options = sphere.SphereTracing(max_steps=budget, over_relaxation=relax)
                fn = lambda s: sphere.march(s.surface, o, wi, options, jnp.zeros(2), 9.0)["t"]  # noqa: E731
                assert _counts(None, fn) == {"_plain": 3}
            for refine in (0, 8):
                options = shadow.SoftShadow(max_steps=budget, refine_steps=refine)
                fn = lambda s: shadow.march(s.surface, o, wi, jnp.asarray(5.0), options)["t"]  # noqa: E731
                assert _counts(None, fn) == {"_plain": 3, **({"golden": 3} if refine else {})}
        for newton, spawn in ((1, 1), (2, 2), (form.PLAIN_UNROLL + 1, 4)):
            settings = jr.RenderSettings(shadows="soft", newton_steps=newton, spawn_steps=spawn)
            counts = _counts(settings)
            polish = newton if newton <= form.PLAIN_UNROLL else 1
            assert counts == {"_plain": 6, "golden": 3, "newton_march": polish,
                              "normal_and_material": 1, "surface_distance": spawn}, counts
    assert form.current() == "phases"


@pytest.mark.parametrize("steps", [1, 2, 3])
def test_origins_settled_together_equal_each_settled_alone(steps):
    """`integrator.spawn_origin` settles the k origins of one hit as a batch: each ends
    where its own `steps` Newton steps take it (float64, to rounding), and next to a
    box's edge, where the first step lands on the level set f = ±offset of the face it
    was pushed off, the origin outside is offset away from the box (f = +offset)."""
    box = jr.sdf.Box(half_extents=(1.0, 1.0, 1.0), material=0)
    scene = jr.Scene(surface=box, materials=[jr.bsdf.Lambert(0.5)], lights=[])
    which = jnp.zeros((), jnp.int32)
    # A hit on the top face, next to its edge with the side face x = 1.
    p = jnp.array([0.999, 1.0, 0.2])
    n = jnp.array([0.0, 1.0, 0.0])
    offset = jnp.asarray(0.01)
    toward, outside = jnp.array([1.0, -1.0]), jnp.array([1.0, -1.0])
    together = integrator.spawn_origin(scene, which, jnp.stack([p, p]), toward[:, None] * n,
                                       jnp.stack([offset, offset]), outside, steps=steps)
    for k in range(2):
        alone = integrator.spawn_origin(scene, which, p, toward[k] * n, offset, outside[k],
                                        steps=steps)
        np.testing.assert_allclose(together[k], alone, rtol=0, atol=1e-15)
    # Outside, after enough steps to clear both faces: f = +offset.
    if steps >= 2:
        assert float(box(together[0])) == pytest.approx(0.01, rel=1e-9)
