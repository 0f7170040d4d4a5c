"""The shipped scenes render clean, and the glass they show matches closed forms.

The water box of configs/scenes/glass_spheres.toml used to rest *exactly* on the floor
plane: the box's bottom face and the plane coincided, so the union of the two had no
surface there (inside the box is next to inside the floor), and every refracted ray that
went down through the water travelled on into the solid floor: blocky black and
background-coloured cells along the bottom of the box. The box now stands 0.01 above the
floor (more than the spawn offset, 4·ε, and far more than ε); the closed form below checks
the box's optics, and `test_no_coincident_faces_in_shipped_scenes` the scene files.
"""

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
