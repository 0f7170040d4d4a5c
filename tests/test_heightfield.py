"""Height fields: marched hits against closed forms and a bisection reference, the notes'
two optimisations measured, normals, implicit-function gradients, extremes."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt.heightfield import GridHeight, HeightField, PlaneHeight, SineHeight

S64 = jr.RenderSettings(dtype="float64", max_distance=40.0)
SINE = SineHeight(amplitude=0.3, frequency=(1.3, 0.9), phase=(0.2, -0.4), offset=0.1)


def _rays(n, seed=0, below=False):
    """Rays from a box above (or below) the surface, pointing down (up) at 10°–80°
    from the vertical."""
    rng = np.random.default_rng(seed)
    o = np.stack([rng.uniform(-3, 3, n), rng.uniform(1.0, 3.0, n), rng.uniform(-3, 3, n)], axis=1)
    theta = np.radians(rng.uniform(10.0, 80.0, n))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), -np.cos(theta), np.sin(theta) * np.sin(phi)], axis=1)
    if below:
        o[:, 1] *= -1.0
        d[:, 1] *= -1.0
    return jnp.asarray(o), jnp.asarray(d)


@eqx.filter_jit
def _intersect(field, o, d, settings):
    return jax.vmap(lambda oi, di: field.intersect(oi, di, settings))(o, d)


def _bisection_reference(height, o, d, t_max=40.0, dt=4e-3):
    """First sign change of g(t) = y − h(x, z) on a fine scan, then 60 bisections (numpy)."""
    o, d = np.asarray(o), np.asarray(d)
    a, f, ph, off = (np.asarray(x) for x in (height.amplitude, height.frequency, height.phase, height.offset))

    def g(oo, dd, t):
        p = oo[..., None, :] + t[..., None] * dd[..., None, :]
        return p[..., 1] - (off + a * np.sin(f[0] * p[..., 0] + ph[0]) * np.cos(f[1] * p[..., 2] + ph[1]))

    ts = np.arange(0.0, t_max, dt)
    t_out, hit_out = [], []
    for oo, dd in zip(np.array_split(o, max(1, len(o) // 32)), np.array_split(d, max(1, len(o) // 32))):
        gs = g(oo, dd, ts)
        s0 = np.sign(gs[:, :1])
        crossed = (gs * s0) <= 0.0
        hit = crossed.any(axis=1)
        k = np.argmax(crossed, axis=1)
        lo = np.where(hit, ts[np.maximum(k - 1, 0)], 0.0)
        hi = np.where(hit, ts[k], 0.0)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            below = g(oo, dd, mid[:, None])[:, 0] * s0[:, 0] <= 0.0
            hi = np.where(below, mid, hi)
            lo = np.where(below, lo, mid)
        t_out.append(0.5 * (lo + hi))
        hit_out.append(hit)
    return np.concatenate(t_out), np.concatenate(hit_out)


# --- closed forms ----------------------------------------------------------------------


@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.35, -0.2)], ids=["plane", "tilted"])
def test_plane_hits_match_closed_form(slope):
    """t = (c + s·o_xz − o_y) / (d_y − s·d_xz) for y = c + s_x x + s_z z; the linear
    interpolation alone is exact on a plane (no Newton step)."""
    height = PlaneHeight(slope=slope, offset=-0.25)
    o, d = _rays(256, seed=1)
    s = np.asarray(slope)
    t_ref = (-0.25 + np.asarray(o)[:, [0, 2]] @ s - np.asarray(o)[:, 1]) / (
        np.asarray(d)[:, 1] - np.asarray(d)[:, [0, 2]] @ s)
    for newton in (0, 1):
        hit = _intersect(HeightField(height), o, d, S64.replace(newton_steps=newton))
        ok = (t_ref > 0.0) & (t_ref < S64.max_distance)
        assert np.all(np.asarray(hit.hit) == ok)
        assert np.max(np.abs(np.asarray(hit.t)[ok] - t_ref[ok])) < 1e-9


def test_sine_surface_against_bisection():
    """Default settings (min_step 0.01, rel_step 0.02, 3 refine steps, one Newton step):
    depth error ≤ 1e-9 in float64 against a bisection reference (measured: ~1e-14),
    from above and from below."""
    for below in (False, True):
        o, d = _rays(256, seed=2, below=below)
        t_ref, hit_ref = _bisection_reference(SINE, o, d)
        hit = _intersect(HeightField(SINE), o, d, S64)
        assert np.all(np.asarray(hit.hit) == hit_ref)
        assert np.all(np.asarray(hit.inside) == below)
        err = np.abs(np.asarray(hit.t) - t_ref)[hit_ref]
        print(f"\nsine height field, {'below' if below else 'above'}: depth error at default "
              f"settings max {err.max():.2e}, median {np.median(err):.2e}; "
              f"steps mean {np.asarray(hit.steps).mean():.1f}")
        assert err.max() < 1e-9


def test_optimisations_of_the_notes():
    """Measure both optimisations on the sine surface (no refinement or Newton polish,
    so that the notes' march alone is compared): linear interpolation shrinks the depth error from O(dt)
    to O(dt²); a step growing with distance saves steps at a bounded error."""
    # A terrain view: eyes 1 above the mean level looking 4°–20° below the horizon,
    # so that rays travel far inside the slab of the waves (t ≈ 1.5–20).
    rng = np.random.default_rng(3)
    n = 512
    elevation = np.radians(rng.uniform(4.0, 20.0, n))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    o = jnp.asarray(np.stack([rng.uniform(-3, 3, n), np.full(n, 1.1), rng.uniform(-3, 3, n)], 1))
    d = jnp.asarray(np.stack([np.cos(elevation) * np.cos(phi), -np.sin(elevation),
                              np.cos(elevation) * np.sin(phi)], 1))
    t_ref, hit_ref = _bisection_reference(SINE, o, d)
    march = S64.replace(newton_steps=0)

    def run(**kw):
        hit = _intersect(HeightField(SINE, max_steps=4096, refine_steps=0, **kw), o, d, march)
        assert np.all(np.asarray(hit.hit) == hit_ref)
        err = np.abs(np.asarray(hit.t) - t_ref)[hit_ref]
        return err, np.asarray(hit.steps)[hit_ref]

    rows = {
        "constant step, first sample below": run(rel_step=0.0, interpolate=False),
        "constant step, interpolated": run(rel_step=0.0),
        "growing step, first sample below": run(interpolate=False),
        "growing step, interpolated (default)": run(),
    }
    print(f"\nheight-field march (min_step 0.01, rel_step 0.02 or 0, no refinement), 512 rays, "
          f"t = {t_ref[hit_ref].min():.1f}–{t_ref[hit_ref].max():.1f}:")
    for name, (err, steps) in rows.items():
        print(f"  {name:38s} mean steps {steps.mean():7.1f}   depth error max {err.max():.2e} "
              f"mean {err.mean():.2e}")
    (e_cf, s_cf), (e_ci, s_ci), (e_gf, s_gf), (e_gi, s_gi) = rows.values()
    assert e_ci.mean() < 0.05 * e_cf.mean()
    assert e_gi.mean() < 0.05 * e_gf.mean()
    assert s_gi.mean() < 0.5 * s_ci.mean()
    # Without interpolation the error is at most the step at the hit, max(0.01, 0.02 t).
    assert np.all(e_gf <= np.maximum(0.01, 0.02 * t_ref[hit_ref]) + 1e-12)
    # The first sample below the surface overshoots by at most one step.
    assert e_cf.max() <= 0.01 + 1e-12


# --- normals, grid, SDF interface ----------------------------------------------------------


def test_normal_is_the_height_gradient_normal():
    x, z = np.random.default_rng(4).uniform(-3, 3, (2, 16))
    a, f, ph = 0.3, (1.3, 0.9), (0.2, -0.4)
    hx = a * f[0] * np.cos(f[0] * x + ph[0]) * np.cos(f[1] * z + ph[1])
    hz = -a * f[1] * np.sin(f[0] * x + ph[0]) * np.sin(f[1] * z + ph[1])
    n_ref = np.stack([-hx, np.ones_like(hx), -hz], 1) / np.sqrt(1 + hx * hx + hz * hz)[:, None]
    p = jnp.asarray(np.stack([x, np.full_like(x, 5.0), z], 1))
    n = jax.jit(jax.vmap(HeightField(SINE).normal))(p)
    assert np.allclose(n, n_ref, atol=1e-12)


def test_grid_height_bilinear():
    """A grid sampled from a plane reproduces the plane (bilinear is exact on it), and
    the grid returns its samples at the nodes."""
    xs, zs = np.linspace(-2, 3, 6), np.linspace(-1, 1, 5)
    plane = PlaneHeight(slope=(0.3, -0.7), offset=0.2)
    heights = 0.2 + 0.3 * xs[None, :] - 0.7 * zs[:, None]
    grid = GridHeight(heights, extent=(-2, 3, -1, 1))
    rng = np.random.default_rng(5)
    x, z = rng.uniform(-2, 3, 16), rng.uniform(-1, 1, 16)
    evaluate = eqx.filter_jit(lambda h, x, z: jax.vmap(h)(x, z))
    assert np.allclose(evaluate(grid, x, z), evaluate(plane, x, z), atol=1e-12)
    bumpy = GridHeight(rng.normal(size=(5, 6)), extent=(-2, 3, -1, 1))
    gx, gz = np.meshgrid(xs, zs)
    assert np.allclose(evaluate(bumpy, gx.ravel(), gz.ravel()), np.asarray(bumpy.heights).ravel(), atol=1e-12)
    o, d = _rays(64, seed=6)
    o = o * jnp.array([0.3, 1.0, 0.3])
    hit_g = _intersect(HeightField(grid), o, d, S64)
    hit_p = _intersect(HeightField(plane), o, d, S64)
    inside = (np.abs(np.asarray(o + hit_p.t[:, None] * d)[:, [0, 2]]) < [[2.0, 1.0]]).all(axis=1)
    assert inside.sum() > 16
    assert np.allclose(np.asarray(hit_g.t)[inside], np.asarray(hit_p.t)[inside], atol=1e-9)


def test_sdf_bound_and_sphere_tracing_agree():
    """`eval` is a distance bound (never more than the true distance to the graph), and
    sphere tracing that bound finds the same hits as the height-field march."""
    rng = np.random.default_rng(7)
    field = HeightField(SINE)
    pts = rng.uniform(-3, 3, (64, 3))
    grid = np.stack(np.meshgrid(np.linspace(-6, 6, 241), np.linspace(-6, 6, 241)), -1).reshape(-1, 2)
    surf = np.stack([grid[:, 0], np.asarray(jax.jit(jax.vmap(SINE))(grid[:, 0], grid[:, 1])), grid[:, 1]], -1)
    true = np.min(np.linalg.norm(pts[:, None, :] - surf[None], axis=-1), axis=1)
    bound = np.abs(np.asarray(jax.jit(jax.vmap(field))(jnp.asarray(pts))))
    assert np.all(bound <= true + 1e-9)
    o, d = _rays(64, seed=8)
    marched = _intersect(field, o, d, S64)
    traced = eqx.filter_jit(jax.vmap(lambda oi, di: jr.sphere_trace(field, oi, di, S64.replace(max_steps=512))))(o, d)
    both = np.asarray(marched.hit) & np.asarray(traced.hit)
    assert both.mean() > 0.95
    assert np.allclose(np.asarray(marched.t)[both], np.asarray(traced.t)[both], atol=1e-6)


# --- gradients and extremes -----------------------------------------------------------


def test_hit_gradient_matches_finite_differences():
    """dt/dθ from the implicit-function Newton step vs central differences (float64)
    for the amplitude of a sine and one sample of a grid."""
    o = jnp.array([0.4, 2.0, -0.3])
    d = jnp.array([0.45, -0.8, 0.2])
    d = d / jnp.linalg.norm(d)
    polished = S64.replace(newton_steps=3)

    def check(make, theta, h=1e-6, default_too=True):
        @jax.jit
        def t_and_grads(th):
            t = lambda s: lambda v: HeightField(make(v)).intersect(o, d, s).t  # noqa: E731
            t_up, t_down, t0 = jax.vmap(t(polished))(jnp.stack([th + h, th - h, th]))
            return t_up, t_down, jax.grad(t(polished))(th), jax.grad(t(S64))(th), t0

        t_up, t_down, grad, grad1, t0 = t_and_grads(theta)
        fd = (t_up - t_down) / (2 * h)
        assert np.isclose(grad, fd, rtol=1e-6, atol=1e-9), (grad, fd)
        if default_too:  # the default single Newton step carries the same gradient
            assert np.isclose(grad1, grad, rtol=1e-6)
        return t0

    check(lambda a: SineHeight(a, (1.3, 0.9), (0.2, -0.4), 0.1), 0.3)
    base = np.random.default_rng(9).uniform(-0.3, 0.3, (4, 4))

    def grid(v):
        return GridHeight(jnp.asarray(base).at[1, 2].set(v), extent=(-1.0, 2.0, -1.5, 1.5))

    # On a bilinear grid the default refinement can stop short of rounding (the height
    # has kinks at cell edges), so compare the polished gradient only.
    t0 = check(grid, 0.1, default_too=False)
    p_hit = o + t0 * d
    assert -1.0 < p_hit[0] < 2.0 and -1.5 < p_hit[2] < 1.5
    # A flat plane: dt/d(offset) = 1 / d_y exactly.
    g = jax.jit(jax.grad(lambda c: HeightField(PlaneHeight(offset=c)).intersect(o, d, S64).t))(0.0)
    assert np.isclose(g, 1.0 / d[1], rtol=1e-12)


def test_finite_at_extremes():
    """Grazing rays, horizontal rays, rays along the surface, rays that start on it and
    rays that miss stay finite, values and gradients (float32, the default)."""
    field = HeightField(SINE)
    o = jnp.array([[0.0, 2.0, 0.0], [0.0, 0.1 + 0.3 * np.sin(0.2) * np.cos(-0.4), 0.0],
                   [0.0, 5.0, 0.0], [0.0, -5.0, 0.0], [1.0, 0.45, 0.0], [0.0, 1.0, 0.0]])
    d = jnp.array([[1.0, -1e-7, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0],
                   [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    for settings in (S64.replace(dtype="float32"),):
        dtype = jnp.float32
        oo, dd = o.astype(dtype), d.astype(dtype)
        f = jax.tree_util.tree_map(lambda x: x.astype(dtype) if eqx.is_array(x) else x, field)
        hit = _intersect(f, oo, dd, settings)
        assert np.all(np.isfinite(np.asarray(hit.t)))
        assert not bool(hit.hit[2]) and not bool(hit.hit[3])

        def loss(fl):
            h = jax.vmap(lambda oi, di: fl.intersect(oi, di, settings))(oo, dd)
            p = oo + h.t[:, None] * dd
            return jnp.sum(jnp.where(h.hit, h.t, 0.0)) + jnp.sum(jax.vmap(fl.normal)(p))

        grads = eqx.filter_jit(eqx.filter_grad(loss))(f)
        assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree_util.tree_leaves(grads))


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match="min_step"):
        HeightField(SINE, min_step=0.0)
    with pytest.raises(ValueError, match="max_steps"):
        HeightField(SINE, max_steps=0)
    with pytest.raises(TypeError, match="height"):
        HeightField(lambda x, z: x)
    with pytest.raises(ValueError, match="extent"):
        GridHeight(np.zeros((3, 3)), extent=(1.0, 0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="heights"):
        GridHeight(np.zeros(3), extent=(0.0, 1.0, 0.0, 1.0))
