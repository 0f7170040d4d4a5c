"""jaxrt.sharding: a render sharded over several devices is the unsharded render.

XLA's device count must be set before jax is imported, so the checks run in a
subprocess with four virtual CPU devices (XLA_FLAGS=--xla_force_host_platform_device_count=4).
"""

import os
import subprocess
import sys
import textwrap

import pytest
from conftest import subprocess_env

SCRIPT = textwrap.dedent(
    """
    import warnings
    import equinox as eqx
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import jaxrt as jr
    from jaxrt.sharding import shard_views

    assert len(jax.devices()) == 4, jax.devices()
    S = jr.sdf
    scene = jr.Scene(
        surface=S.Union(S.Translate(S.Sphere(radius=0.6, material=0), offset=(0.0, 0.6, 0.0)),
                        S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
        materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)), jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6))],
        lights=[jr.PointLight(position=(2.0, 4.0, 3.0), intensity=(30.0, 30.0, 30.0))],
        background=(0.1, 0.1, 0.15))
    camera = jr.PerspectiveCamera(eye=(0.0, 1.5, 3.5), target=(0.0, 0.5, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=45.0, width=12, height=8)
    base = jr.RenderSettings(shadows="soft", batch_size=32, dtype="float64")
    one = jr.render(scene, camera, base)
    # 12 columns on 4 devices (even), 8 rows on 3 (uneven, padded); the jax and the fused
    # backends (the Pallas kernel, which computes each block's pixel centres from its
    # offset, in float32 and interpret mode: on 3 devices, by columns and by rows)
    fields = ("rgb", "depth", "normal", "albedo", "steps", "coverage")

    def on_lanes(scene, settings):  # the render, where "auto" must not fall back to "jax"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            img = jr.render(scene, camera, settings)
        fell_back = [str(w.message) for w in caught if "rendering with backend" in str(w.message)]
        assert not fell_back, fell_back
        return img

    for split, devices in (("columns", 4), ("rows", 3)):  # settings are the cache key
        img = on_lanes(scene, base.replace(devices=devices, split=split))
        for field in fields:
            a, b = np.asarray(getattr(img, field)), np.asarray(getattr(one, field))
            assert np.allclose(a, b, rtol=1e-12, atol=1e-12), (split, devices, field,
                                                               np.abs(a - b).max())
    # a ray tree in one scan (recursion = "scan": its slot buffer is where JAX inserts a
    # `reshard` under shard_map), on 2 devices, on the fused lanes too
    mirror = eqx.tree_at(lambda s: s.materials, scene, [jr.bsdf.Mirror(), scene.materials[1]])
    tree = base.replace(max_depth=1, recursion="scan")
    want = jr.render(mirror, camera, tree)
    got = on_lanes(mirror, tree.replace(devices=2))
    assert np.allclose(got.rgb, want.rgb, rtol=1e-12, atol=1e-12), np.abs(got.rgb - want.rgb).max()
    f32 = base.replace(dtype="float32", backend="pallas", batch_size=16)
    want = jr.render(scene, camera, f32)
    for split in ("columns", "rows"):
        got = jr.render(scene, camera, f32.replace(devices=3, split=split))
        for field in fields:
            a, b = np.asarray(getattr(got, field)), np.asarray(getattr(want, field))
            assert np.allclose(a, b, rtol=1e-5, atol=1e-5), (split, "pallas", field,
                                                             np.abs(a - b).max())
    from jaxrt.sharding import shard_image
    grid = jnp.stack(jnp.meshgrid(jnp.arange(10.0), jnp.arange(7.0), indexing="ij"), -1)
    for split in ("rows", "columns"):  # each device sees its block and its offset
        got = shard_image(lambda rep, s, g, off: {"s": s, "o": jnp.broadcast_to(
            jnp.stack(off), (s.shape[0], 2))}, (), grid.reshape(-1, 2), (10, 7),
            jax.devices()[:3], split=split)
        assert np.array_equal(np.asarray(got["s"]), np.asarray(grid)), (split, got["s"])
        r, c = np.meshgrid(np.arange(10), np.arange(7), indexing="ij")
        want = np.stack([r // 4 * 4, 0 * c] if split == "rows" else [0 * r, c // 3 * 3], -1)
        assert np.array_equal(np.asarray(got["o"]), want), (split, got["o"])
    img = jr.render(scene, camera, base.replace(devices=4))
    assert len(img.rgb.sharding.device_set) == 4, img.rgb.sharding
    assert img.rgb.sharding.spec == jax.sharding.PartitionSpec(None, "pixels"), img.rgb.sharding
    try:
        jr.render(scene, camera, base.replace(devices=5))
    except ValueError as e:
        assert "devices = 5" in str(e) and "4 local devices" in str(e), e
    else:
        raise AssertionError("devices=5 on 4 devices did not raise")

    # views sharded for fitting: the summed loss and its gradient are the unsharded ones
    def loss(p, view):
        return jnp.sum((jnp.sin(view * p[0]) + p[1]) ** 2)
    views = jnp.linspace(0.0, 1.0, 8).reshape(8, 1)
    p = jnp.array([1.3, -0.2])
    want = sum(loss(p, v) for v in views)
    got = shard_views(loss, p, views)
    assert np.allclose(got, want), (got, want)
    g_want = jax.grad(lambda q: sum(loss(q, v) for v in views))(p)
    g_got = jax.grad(lambda q: shard_views(loss, q, views))(p)
    assert np.allclose(g_got, g_want), (g_got, g_want)
    print("OK")
    """
)


def test_sharded_render_is_the_unsharded_render(tmp_path):
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
    env = subprocess_env(XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    script = tmp_path / "sharded.py"
    script.write_text(SCRIPT)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env,
                          timeout=600)
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]


def test_devices_setting_is_validated():
    import jaxrt as jr

    with pytest.raises(ValueError, match="devices"):
        jr.RenderSettings(devices=-1)
