"""Gradients over several devices equal the gradients on one (issue 15).

`value_and_grad` of an image loss with the image sharded over devices
(`RenderSettings(devices=D)`: blocks of columns, even and uneven splits) and of a
multi-view loss with the views sharded (`render_views(devices=D)`) give the unsharded
value and gradient, in float64, to 1e-10 relative. XLA's device count must be set before
jax is imported, so the checks run in a subprocess with four virtual CPU devices.
"""

import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np
    import jaxrt as jr

    assert len(jax.devices()) == 4, jax.devices()
    S = jr.sdf
    scene = jr.Scene(
        surface=S.Union(S.Translate(S.Sphere(radius=0.6, material=0), offset=(0.0, 0.6, 0.0)),
                        S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
        materials=[jr.bsdf.CookTorrance(distribution=jr.bsdf.GGX(0.3)),
                   jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6))],
        lights=[jr.PointLight(position=(2.0, 4.0, 3.0), intensity=(30.0, 30.0, 30.0))],
        background=(0.1, 0.1, 0.15))
    camera = jr.PerspectiveCamera(eye=(0.0, 1.5, 3.5), target=(0.0, 0.5, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=45.0, width=10, height=7)

    def close(got, want, what):
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            a, b = np.asarray(a), np.asarray(b)
            scale = max(np.max(np.abs(b)), 1e-30)
            assert np.max(np.abs(a - b)) <= 1e-10 * scale, (what, np.max(np.abs(a - b)) / scale)

    def image_loss(params, settings):
        scene_, camera_ = params
        return jnp.mean(jr.render(scene_, camera_, settings).rgb ** 2)

    grad = eqx.filter_value_and_grad(image_loss)
    for backend in ("jax", "fused"):
        base = jr.RenderSettings(shadows="soft", batch_size=32, dtype="float64", backend=backend,
                                 aovs=())
        want = grad((scene, camera), base)
        assert float(want[0]) > 0 and any(
            np.any(np.asarray(g) != 0) for g in jax.tree_util.tree_leaves(want[1]))
        for devices in (4, 3):   # 10 columns: uneven on both (padded)
            close(grad((scene, camera), base.replace(devices=devices)), want, (backend, devices))

    # Views sharded: the summed multi-view loss and its gradient are the unsharded ones.
    cameras = jr.views.orbit(4, target=(0.0, 0.5, 0.0), distance=3.5, elevation=20.0,
                             width=8, height=6)
    settings = jr.RenderSettings(dtype="float64", batch_size=32, aovs=())

    def views_loss(params, devices):
        scene_, cameras_ = params
        return jnp.mean(jr.render_views(scene_, cameras_, settings, devices=devices).rgb ** 2)

    vgrad = eqx.filter_value_and_grad(views_loss)
    want = vgrad((scene, cameras), None)
    for devices in (4, 2):
        close(vgrad((scene, cameras), devices), want, ("views", devices))
    print("OK")
    """
)


@pytest.mark.slow  # compiles ten value_and_grad programs: about 2 minutes on 2 quiet cores
def test_sharded_gradients_are_the_unsharded_gradients(tmp_path):
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
    env["JAX_PLATFORMS"] = "cpu"
    script = tmp_path / "sharded_gradients.py"
    script.write_text(SCRIPT)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env,
                          timeout=900)
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]
