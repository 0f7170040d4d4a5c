"""`jaxrt.sdf.Grid`: a voxel grid of signed distances against the analytic shapes it
samples, its Lipschitz bound against random pairs of points, its gradients against
float64 finite differences, and the fitting helpers (upsample, redistance, eikonal)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import sdf
from jaxrt.config import ConfigError, loads, load
from jaxrt.render import PER_SAMPLE_MAX

LO, HI = (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)
R = 0.7


def sphere_grid(n, radius=R):
    return sdf.Grid.from_sdf(sdf.Sphere(radius), LO, HI, n)


def points(seed, n=2000, lo=-1.0, hi=1.0):
    return np.random.default_rng(seed).uniform(lo, hi, (n, 3))


def test_sphere_grid_is_second_order():
    """Trilinear samples of |p| − r: error O(h²) inside and near the surface (away
    from the kink at the centre), so halving h divides it by ≈ 4."""
    p = points(0)
    r = np.linalg.norm(p, axis=1)
    band = (r > 0.3) & (r < 0.95)
    errors = []
    for n in (17, 33, 65):
        g = sphere_grid(n)
        errors.append(np.abs(np.asarray(jax.vmap(g)(p)) - (r - R))[band].max())
    h = 2.0 / 64
    assert errors[-1] < 1.0 * h * h / (2 * 0.3)  # |∇²| of |p| is ≤ 2/|p| per direction
    assert errors[0] / errors[1] > 3.0 and errors[1] / errors[2] > 3.0
    # exact where the field is linear along the grid: the samples themselves
    g = sphere_grid(9)
    x = np.asarray(g.points()).reshape(-1, 3)
    np.testing.assert_allclose(jax.vmap(g)(x), np.linalg.norm(x, axis=1) - R, atol=1e-12)


def test_outside_is_distance_to_box_plus_boundary_value():
    g = sphere_grid(17)
    p = points(1, lo=-4.0, hi=4.0)
    c = np.clip(p, -1.0, 1.0)
    expected = np.linalg.norm(p - c, axis=1) + np.asarray(jax.vmap(g.interpolate)(c))
    np.testing.assert_allclose(jax.vmap(g)(p), expected, atol=1e-12)
    # f/L never overestimates the distance to the sphere: a ray marches to it safely
    # (f itself can: the boundary value at c(p) need not be the smallest on the box)
    f = np.abs(np.asarray(jax.vmap(g)(p))) / float(g.lipschitz())
    assert np.all(f <= np.abs(np.linalg.norm(p, axis=1) - R) + 1e-2)


@pytest.mark.parametrize("kind", ["sphere", "noise", "torus_box"])
def test_lipschitz_bound_holds_on_random_pairs(kind):
    if kind == "sphere":
        g = sphere_grid(13)
    elif kind == "noise":  # far from a distance field: steep, random samples
        v = np.random.default_rng(2).normal(0.0, 0.3, (7, 9, 6))
        g = sdf.Grid(v, (-1.0, -0.5, -1.0), (1.0, 1.5, 0.2))
    else:
        node = sdf.Subtraction(sdf.Box((0.6, 0.3, 0.6)), sdf.Torus(0.5, 0.2))
        g = sdf.Grid.from_sdf(node, LO, HI, 11)
    L = float(g.lipschitz())
    rng = np.random.default_rng(3)
    p = rng.uniform(-2.0, 2.0, (5000, 3))
    q = p + rng.normal(0.0, 1.0, p.shape) * rng.choice([1e-3, 1e-2, 0.3], (len(p), 1))
    f = jax.jit(jax.vmap(g))
    ratio = np.abs(np.asarray(f(p) - f(q))) / np.linalg.norm(p - q, axis=1)
    assert ratio.max() <= L * (1 + 1e-9)
    assert ratio.max() > 0.5 * L  # not vacuous
    # |∇f| ≤ L everywhere too
    grads = np.linalg.norm(np.asarray(jax.jit(jax.vmap(jax.grad(g)))(p)), axis=1)
    assert grads.max() <= L * (1 + 1e-9)
    if kind == "sphere":
        assert L <= np.sqrt(3.0) + 1e-9


def test_gradient_wrt_values_matches_finite_differences():
    """d f(p) / d values and the traced hit distance's gradient, against central
    differences in float64."""
    g = sphere_grid(9)
    settings = jr.RenderSettings(dtype="float64", hit_epsilon=1e-10, max_steps=256,
                                 newton_steps=3)
    o, d = jnp.array([0.13, 0.21, -3.0]), jnp.array([0.0, 0.0, 1.0])

    @jax.jit
    def t_hit(values):
        return jr.sphere_trace(eqx.tree_at(lambda s: s.values, g, values), o, d, settings).t

    @jax.jit
    def f_at(values):
        return eqx.tree_at(lambda s: s.values, g, values)(jnp.array([0.31, -0.22, 0.45]))

    v = g.values
    rng = np.random.default_rng(4)
    for fn in (f_at, t_hit):
        grad = jax.grad(fn)(v)
        assert np.count_nonzero(np.asarray(grad)) >= 4
        hot = np.argwhere(np.asarray(grad) != 0.0)
        for idx in hot[rng.choice(len(hot), min(6, len(hot)), replace=False)]:
            e = jnp.zeros_like(v).at[tuple(idx)].set(1e-6)
            fd = (fn(v + e) - fn(v - e)) / 2e-6
            np.testing.assert_allclose(grad[tuple(idx)], fd, rtol=1e-5, atol=1e-9)
        # a random direction through all samples at once
        dv = jnp.asarray(rng.normal(size=v.shape))
        fd = (fn(v + 1e-6 * dv) - fn(v - 1e-6 * dv)) / 2e-6
        np.testing.assert_allclose(jnp.vdot(grad, dv), fd, rtol=1e-5, atol=1e-9)


def test_values_and_gradients_finite_far_away_and_on_the_box():
    g = sphere_grid(9)
    faces = np.array([[1.0, 0.3, -0.2], [-1.0, 1.0, 0.5], [1.0, 1.0, -1.0], [0.0, -1.0, 0.0],
                      [1e6, 0.0, 0.0], [-1e12, 3e11, 1e12], [1.0 + 1e-12, 0.5, 0.5]])
    values = jax.vmap(g)(faces)
    grads = jax.vmap(jax.grad(g))(faces)
    gv = jax.vmap(jax.grad(lambda vals, p: eqx.tree_at(lambda s: s.values, g, vals)(p)),
                  in_axes=(None, 0))(g.values, faces)
    assert np.all(np.isfinite(values)) and np.all(np.isfinite(grads)) and np.all(np.isfinite(gv))
    # on a face the gradient is the interpolant's (not halved by the clamp)
    np.testing.assert_allclose(np.linalg.norm(grads[3]), 1.0, atol=0.1)
    # far away the value grows like the distance, the gradient is a unit vector plus the
    # boundary value's tangential slope
    np.testing.assert_allclose(values[4], 1e6 - 1.0 + g.interpolate(jnp.array([1.0, 0.0, 0.0])))
    assert 1.0 <= np.linalg.norm(grads[4]) <= float(g.lipschitz()) + 1e-9


@pytest.mark.slow  # two renderer compilations: ~30 s on 2 busy cores
def test_render_matches_analytic_sphere():
    """The image of a 33³ Grid sphere against the analytic Sphere's: same coverage up to
    a few outline pixels, shading within a few percent (faceted normals)."""
    materials = [jr.bsdf.Lambert(albedo=(0.8, 0.7, 0.6))]
    lights = [jr.DirectionalLight(direction=(-0.3, -1.0, 0.5), irradiance=(3.0, 3.0, 3.0))]
    camera = jr.PerspectiveCamera(eye=(0.4, 0.6, -3.0), target=(0.0, 0.0, 0.0),
                                  up=(0.0, 1.0, 0.0), fov=40.0, width=24, height=24)
    settings = jr.RenderSettings(shadows="none", aovs=("coverage",))

    def image(surface):
        scene = jr.Scene(surface=surface, materials=materials, lights=lights, background=(0.1, 0.1, 0.1))
        return jr.render(scene, camera, settings)

    ref, img = image(sdf.Sphere(R)), image(sphere_grid(33))
    assert np.asarray(ref.coverage).mean() > 0.2
    assert np.sum(np.asarray(ref.coverage) != np.asarray(img.coverage)) <= 3
    err = np.abs(np.asarray(img.rgb - ref.rgb)).max(axis=-1)
    assert np.sum(err > 0.05) <= 3 and np.median(err[np.asarray(ref.coverage) > 0]) < 0.01


def test_grid_in_csg_and_placements():
    """A Grid is a node like any other: the combinations see its distances and material."""
    g = sdf.Grid.from_sdf(sdf.Sphere(0.5), (-0.8,) * 3, (0.8,) * 3, 41)
    g = sdf.Grid(g.values, g.lower, g.upper, material=2)
    s = sdf.Translate(sdf.Sphere(0.3, material=1), (0.5, 0.0, 0.0))
    exact_g = sdf.Sphere(0.5, material=2)
    p = points(5, n=500, lo=-0.65, hi=0.65)  # translated, still inside the grid's box
    for op in (lambda a: sdf.Union(a, s), lambda a: sdf.Subtraction(a, s),
               lambda a: sdf.SmoothUnion(a, s, 0.2), lambda a: sdf.Translate(a, (0.1, 0.0, 0.0)),
               lambda a: sdf.Intersection(a, sdf.Box((0.4, 0.4, 0.4)))):
        d, m = jax.vmap(op(g).eval)(p)
        de, me = jax.vmap(op(exact_g).eval)(p)
        np.testing.assert_allclose(d, de, atol=1e-2)  # the sampled kink at the centre: ≤ h/4
        assert np.mean(np.asarray(m) == np.asarray(me)) > 0.98
    assert sdf.Union(g, s).material_ids() == {1, 2}
    assert float(sdf.Union(g, s).lipschitz()) == pytest.approx(float(g.lipschitz()))


def test_from_sdf_takes_the_material_and_resolution():
    node = sdf.Union(sdf.Sphere(0.5, material=3), sdf.Translate(sdf.Sphere(0.2, material=1), (0.5, 0, 0)))
    g = sdf.Grid.from_sdf(node, LO, HI, (5, 6, 7))
    assert g.values.shape == (5, 6, 7) and g.material == 1
    with pytest.raises(ValueError, match="resolution"):
        sdf.Grid.from_sdf(node, LO, HI, 1)
    with pytest.raises(TypeError, match="node"):
        sdf.Grid.from_sdf(lambda p: 0.0, LO, HI, 4)


def test_constructor_errors():
    with pytest.raises(ValueError, match=r"\[nx, ny, nz\]"):
        sdf.Grid(np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"\[nx, ny, nz\]"):
        sdf.Grid(np.zeros((4, 1, 4)))
    with pytest.raises(ValueError, match="finite"):
        sdf.Grid(np.full((2, 2, 2), np.nan))
    with pytest.raises(ValueError, match="lower < upper"):
        sdf.Grid(np.zeros((2, 2, 2)), (0, 0, 0), (1, 0, 1))
    with pytest.raises(ValueError, match="material"):
        sdf.Grid(np.zeros((2, 2, 2)), material=-1)


def test_upsample_preserves_the_interpolant():
    """An integer factor keeps every old vertex, and the trilinear interpolant of a
    multilinear function restricted to a sub-cell is itself: the shape is unchanged."""
    v = np.random.default_rng(6).normal(size=(5, 4, 6))
    g = sdf.Grid(v, (-1.0, 0.0, -2.0), (1.0, 0.5, 1.0))
    fine = sdf.upsample(g, 3)
    assert fine.values.shape == (13, 10, 16)
    np.testing.assert_allclose(fine.values[::3, ::3, ::3], v, atol=1e-12)
    p = points(7, lo=-2.5, hi=1.5)
    np.testing.assert_allclose(jax.vmap(fine)(p), jax.vmap(g)(p), atol=1e-12)
    assert sdf.upsample(g, resolution=8).values.shape == (8, 8, 8)
    with pytest.raises(ValueError, match="factor"):
        sdf.upsample(g, 1.5)


def test_redistance_recovers_a_scaled_distance_field():
    g = sphere_grid(33)
    scaled = sdf.Grid(2.0 * g.values, g.lower, g.upper)
    rd = sdf.redistance(scaled)
    h = 2.0 / 32
    v, w = np.asarray(g.values), np.asarray(rd.values)
    near = np.abs(v) < 2.0 * h
    assert np.abs(w - v)[near].max() < 0.15 * h
    assert np.array_equal(np.sign(w), np.sign(np.where(v == 0, 1.0, v)))
    # everywhere a distance field to first order: well within one cell of the truth
    assert np.abs(w - v).max() < 1.5 * h
    # and redistancing a distance field changes it little
    np.testing.assert_allclose(sdf.redistance(g).values, v, atol=1.5 * h)


def test_eikonal_loss():
    plane = sdf.Grid.from_sdf(sdf.Plane((1.0, 2.0, -0.5), 0.2), LO, HI, 7)
    assert float(sdf.eikonal_loss(plane)) < 1e-20
    scaled = sdf.Grid(2.0 * plane.values, plane.lower, plane.upper)
    np.testing.assert_allclose(sdf.eikonal_loss(scaled), 1.0, rtol=1e-9)
    assert float(sdf.eikonal_loss(scaled, band=0.1)) == pytest.approx(1.0)
    g = jax.grad(lambda v: sdf.eikonal_loss(sdf.Grid(v, LO, HI)))(scaled.values)
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0


# -- TOML ---------------------------------------------------------------------------------

SCENE = """
[camera]
eye = [0.0, 0.5, -3.0]
target = [0.0, 0.0, 0.0]
width = 8
height = 8
[materials.clay]
type = "lambert"
albedo = [0.8, 0.8, 0.8]
[materials.red]
type = "lambert"
albedo = [0.8, 0.1, 0.1]
[[lights]]
type = "directional"
direction = [0.0, -1.0, 0.0]
irradiance = [1.0, 1.0, 1.0]
[surface]
type = "union"
children = [
  {{ type = "grid", values = {values}, lower = [-1.0, -1.0, -1.0], upper = {upper}, material = "red" }},
  {{ type = "sphere", radius = 0.1 }},
]
"""


def test_toml_grid_from_npy(tmp_path):
    g = sphere_grid(9)
    np.save(tmp_path / "shape.npy", np.asarray(g.values))
    path = tmp_path / "scene.toml"
    path.write_text(SCENE.format(values='"shape.npy"', upper="[1.0, 1.0, 1.0]"))
    scene, camera, _ = load(path)
    grid = scene.surface.children_[0]
    assert isinstance(grid, sdf.Grid) and grid.material == 1
    np.testing.assert_allclose(grid.values, g.values)
    np.testing.assert_allclose(grid.upper, 1.0)
    # inline nested arrays work too
    inline = SCENE.format(values=np.asarray(sphere_grid(2).values).tolist(), upper="[1.0, 1.0, 1.0]")
    assert loads(inline).__getitem__(0).surface.children_[0].values.shape == (2, 2, 2)


@pytest.mark.parametrize("values, upper, match", [
    ('"missing.npy"', "[1.0, 1.0, 1.0]", r"scene\.toml: surface\.children\[0\]\.values = 'missing\.npy', expected a readable \.npy file"),
    ('"shape.txt"', "[1.0, 1.0, 1.0]", r"surface\.children\[0\]\.values = 'shape\.txt', expected .*\.npy"),
    ('"flat.npy"', "[1.0, 1.0, 1.0]", r"scene\.toml: surface\.children\[0\]: `Grid\(values=\.\.\.\)` must have shape"),
    ('"nan.npy"', "[1.0, 1.0, 1.0]", r"surface\.children\[0\]\.values = 'nan\.npy', expected a \.npy file of finite numbers"),
    ('"shape.npy"', "[1.0, -1.0, 1.0]", r"surface\.children\[0\]: `Grid\(lower=\.\.\., upper=\.\.\.\)` must have lower < upper"),
    ('"shape.npy"', "[1.0, 1.0]", r"surface\.children\[0\]: `Grid\(upper=\.\.\.\)` must have shape \(3,\)"),
])
def test_toml_grid_errors(tmp_path, values, upper, match):
    np.save(tmp_path / "shape.npy", np.zeros((3, 3, 3)))
    np.save(tmp_path / "flat.npy", np.zeros((3, 3)))
    np.save(tmp_path / "nan.npy", np.full((2, 2, 2), np.nan))
    (tmp_path / "shape.txt").write_text("0")
    path = tmp_path / "scene.toml"
    path.write_text(SCENE.format(values=values, upper=upper))
    with pytest.raises(ConfigError, match=match):
        load(path)


def _largest_value(jaxpr):
    """The most elements any value of `jaxpr` holds, nested jaxprs included."""
    sizes = [int(np.prod(v.aval.shape)) for e in jaxpr.eqns for v in e.outvars
             if hasattr(v.aval, "shape")]
    for eqn in jaxpr.eqns:
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else [value]:
                if hasattr(sub, "eqns"):
                    sizes.append(_largest_value(sub))
                elif hasattr(sub, "jaxpr") and hasattr(sub.jaxpr, "eqns"):
                    sizes.append(_largest_value(sub.jaxpr))
    return max(sizes, default=0)


@pytest.mark.slow
def test_grid_image_gradient_is_shared_not_copied_per_sample():
    """The replay of the fast backends ("auto": here the lanes cannot
    run a 3-D gather, so it records with the "jax" loops) keeps a large grid's samples shared:
    no value of the gradient program holds a copy of the grid per ray (a 129³ grid at
    128×128 would take 131 GiB), and its gradient equals the "jax" path's."""
    g = sphere_grid(17)  # 4913 samples: above PER_SAMPLE_MAX
    assert g.values.size > PER_SAMPLE_MAX
    camera = jr.PerspectiveCamera(eye=(0.3, 0.4, -3.0), target=(0.0, 0.0, 0.0), fov=40.0,
                                  width=12, height=12)
    light = jr.DirectionalLight((0.4, 0.7, -0.6), (1.0, 1.0, 1.0))

    def loss(values, backend):
        scene = jr.Scene(eqx.tree_at(lambda s: s.values, g, values), [jr.bsdf.Lambert((0.8, 0.6, 0.4))],
                         [light], background=(0.1, 0.1, 0.1))
        settings = jr.RenderSettings(backend=backend, shadows="none", max_steps=64, aovs=())
        return jnp.mean(jr.render(scene, camera, settings).rgb ** 2)

    grad = {b: jax.jit(jax.grad(lambda v, b=b: loss(v, b)))(g.values) for b in ("jax", "auto")}
    assert np.count_nonzero(np.asarray(grad["jax"])) > 20
    np.testing.assert_allclose(grad["auto"], grad["jax"], rtol=2e-3, atol=1e-6 * float(np.abs(grad["jax"]).max()))
    jaxpr = jax.make_jaxpr(jax.grad(lambda v: loss(v, "auto")))(g.values).jaxpr
    assert _largest_value(jaxpr) < 12 * 12 * g.values.size // 4
