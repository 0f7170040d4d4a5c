"""Cameras: eye rays through pixel centres and stratified pixel samples."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt.camera import pixel_samples

from helpers import unit

EYE, TARGET, UP = (1.0, 2.0, -5.0), (0.3, 0.5, 0.7), (0.1, 1.0, 0.2)


def rays(camera, px, py):
    o, d, cone = jax.vmap(camera.generate_ray)(jnp.asarray(px, float), jnp.asarray(py, float))
    return np.asarray(o), np.asarray(d), np.asarray(cone)


def angle_deg(a, b):
    a, b = unit(a), unit(b)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


@pytest.mark.parametrize("width,height", [(33, 21), (32, 24), (1, 1)])
def test_perspective_centre_ray_points_at_the_target(width, height):
    cam = jr.PerspectiveCamera(EYE, TARGET, UP, fov=50.0, width=width, height=height)
    o, d, _ = rays(cam, [width / 2], [height / 2])
    np.testing.assert_allclose(o[0], EYE, atol=1e-12)
    np.testing.assert_allclose(d[0], unit(np.subtract(TARGET, EYE)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    if width % 2 and height % 2:  # the centre pixel of an odd image is that ray
        s = np.asarray(pixel_samples(cam, 1, 0))
        centre = s[(height // 2) * width + width // 2]
        np.testing.assert_allclose(centre, [width / 2, height / 2])


@pytest.mark.parametrize("fov", [1.0, 40.0, 90.0, 150.0])
def test_perspective_fov_is_vertical_and_orientation_is_upright(fov):
    w, h = 40, 30
    cam = jr.PerspectiveCamera(EYE, TARGET, UP, fov=fov, width=w, height=h)
    forward = unit(np.subtract(TARGET, EYE))
    _, d, _ = rays(cam, [w / 2, w / 2, 0.0, w, w / 2], [0.0, h, h / 2, h / 2, h / 2])
    top, bottom, left, right, centre = d
    np.testing.assert_allclose(angle_deg(top, forward), fov / 2, rtol=1e-9)
    np.testing.assert_allclose(angle_deg(bottom, forward), fov / 2, rtol=1e-9)
    half_h = np.degrees(np.arctan(np.tan(np.radians(fov / 2)) * w / h))
    np.testing.assert_allclose(angle_deg(left, forward), half_h, rtol=1e-9)
    # Up in the image is towards `up`; right is forward × up (right-handed world).
    up_dir = unit(np.cross(np.cross(forward, UP), forward))
    assert np.dot(top - bottom, up_dir) > 0
    assert np.dot(right - left, np.cross(forward, UP)) > 0
    # Rows run top to bottom: pixel row 0 is the top one.
    _, d0, _ = rays(cam, [w / 2], [0.5])
    assert np.dot(d0[0], up_dir) > np.dot(centre, up_dir)


def test_orthographic_rays_are_parallel_and_the_view_has_half_height_size():
    w, h, size = 24, 16, 2.5
    cam = jr.OrthographicCamera(EYE, TARGET, UP, size=size, width=w, height=h)
    forward = unit(np.subtract(TARGET, EYE))
    px, py = np.meshgrid(np.linspace(0, w, 7), np.linspace(0, h, 5))
    o, d, cone = rays(cam, px.ravel(), py.ravel())
    np.testing.assert_allclose(d, np.broadcast_to(forward, d.shape), atol=1e-12)
    # Origins lie in the plane through the eye perpendicular to the view direction.
    np.testing.assert_allclose((o - EYE) @ forward, 0.0, atol=1e-12)
    (top, bottom, left, right), _, _ = rays(cam, [w / 2, w / 2, 0, w], [0, h, h / 2, h / 2])
    np.testing.assert_allclose(np.linalg.norm(top - np.asarray(EYE)), size, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(top - bottom), 2 * size, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(right - left), 2 * size * w / h, rtol=1e-12)
    # The pixel cone of an orthographic camera has a constant radius of half a pixel.
    np.testing.assert_allclose(cone[:, 0], size / h, rtol=1e-12)
    np.testing.assert_allclose(cone[:, 1], 0.0, atol=0)


def test_perspective_pixel_cone_is_half_a_pixel_wide():
    w, h, fov = 20, 10, 60.0
    cam = jr.PerspectiveCamera(EYE, TARGET, UP, fov=fov, width=w, height=h)
    _, d, cone = rays(cam, [w / 2, w / 2], [h / 2, h / 2 + 1.0])
    # Neighbouring pixel centres at the image centre are 2·tan(fov/2)/h apart at unit
    # distance: the cone radius at unit distance is half that.
    gap = np.tan(np.radians(angle_deg(d[0], d[1])))
    np.testing.assert_allclose(cone[0, 1], gap / 2, rtol=1e-9)
    assert cone[0, 0] == 0.0


@pytest.mark.parametrize("spp", [2, 4, 9])
def test_pixel_samples_are_stratified_inside_their_pixel_and_deterministic(spp):
    w, h = 6, 4
    cam = jr.PerspectiveCamera(EYE, TARGET, UP, fov=40.0, width=w, height=h)
    s = np.asarray(pixel_samples(cam, spp, seed=3)).reshape(h, w, spp, 2)
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    local = s - np.stack([cols, rows], axis=-1)[:, :, None, :]
    assert np.all((local >= 0.0) & (local < 1.0))  # inside the pixel
    strata = np.floor(local * spp).astype(int)
    for axis in (0, 1):  # N-rooks: one sample per x stratum and per y stratum
        assert np.all(np.sort(strata[..., axis], axis=-1) == np.arange(spp))
    again = np.asarray(pixel_samples(cam, spp, seed=3)).reshape(h, w, spp, 2)
    np.testing.assert_array_equal(again, s)
    other = np.asarray(pixel_samples(cam, spp, seed=4)).reshape(h, w, spp, 2)
    assert not np.allclose(other, s)
    # The pattern differs between pixels.
    assert not np.allclose(local[0, 0], local[1, 1])


def test_one_sample_per_pixel_is_the_pixel_centre():
    w, h = 5, 3
    cam = jr.OrthographicCamera(EYE, TARGET, UP, size=1.0, width=w, height=h)
    s = np.asarray(pixel_samples(cam, 1, seed=0))
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    np.testing.assert_array_equal(s, np.stack([cols.ravel(), rows.ravel()], axis=-1) + 0.5)


def test_with_resolution_keeps_the_view():
    cam = jr.PerspectiveCamera(EYE, TARGET, UP, fov=35.0, width=16, height=8)
    big = cam.with_resolution(64, 32)
    assert (big.width, big.height) == (64, 32)
    _, d1, _ = rays(cam, [4.0], [2.0])
    _, d2, _ = rays(big, [16.0], [8.0])
    np.testing.assert_allclose(d1, d2, atol=1e-12)
    with pytest.raises(ValueError, match="width"):
        cam.with_resolution(0, 8)


BAD = [
    (lambda: jr.PerspectiveCamera(fov=0.0), "PerspectiveCamera(fov"),
    (lambda: jr.PerspectiveCamera(fov=180.0), "PerspectiveCamera(fov"),
    (lambda: jr.PerspectiveCamera(width=0), "PerspectiveCamera(width"),
    (lambda: jr.PerspectiveCamera(height=2.5), "PerspectiveCamera(height"),
    (lambda: jr.PerspectiveCamera(eye=(1.0, 1.0, 1.0), target=(1.0, 1.0, 1.0)), "eye and target"),
    (lambda: jr.PerspectiveCamera(eye=(0.0, 0.0, 0.0), target=(0.0, 2.0, 0.0), up=(0.0, 1.0, 0.0)),
     "PerspectiveCamera(up"),
    (lambda: jr.PerspectiveCamera(eye=(0.0, float("nan"), 0.0)), "PerspectiveCamera(eye"),
    (lambda: jr.PerspectiveCamera(target=(0.0, 0.0)), "PerspectiveCamera(target"),
    (lambda: jr.OrthographicCamera(size=0.0), "OrthographicCamera(size"),
    (lambda: jr.OrthographicCamera(size=-1.0), "OrthographicCamera(size"),
    (lambda: jr.OrthographicCamera(width=-3), "OrthographicCamera(width"),
    (lambda: jr.PointLight(intensity=(-1.0, 1.0, 1.0)), "PointLight(intensity"),
    (lambda: jr.PointLight(position=(0.0, float("inf"), 0.0)), "PointLight(position"),
    (lambda: jr.DirectionalLight(direction=(0.0, 0.0, 0.0)), "DirectionalLight(direction"),
    (lambda: jr.DirectionalLight(irradiance=(1.0, -2.0, 1.0)), "DirectionalLight(irradiance"),
]


@pytest.mark.parametrize("make,name", BAD, ids=[b[1] for b in BAD])
def test_cameras_and_lights_reject_bad_values_naming_the_argument(make, name):
    with pytest.raises((ValueError, TypeError)) as info:
        make()
    assert name in str(info.value)
