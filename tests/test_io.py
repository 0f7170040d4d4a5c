"""Tests for jaxrt.io: EXR, PNG and MERL files, and atomic writes."""

import os
import struct
import types
import zlib

import colour
import numpy as np
import OpenEXR
import pytest

from jaxrt import io as jio

# --------------------------------------------------------------------------- helpers


def _random_floats(rng, shape):
    """float32 from random bit patterns: normals, denormals, +-0, +-inf and NaNs."""
    bits = rng.integers(0, 2**32, size=shape, dtype=np.uint64).astype(np.uint32)
    return bits.view(np.float32)


def _decode_png(path):
    """Minimal independent PNG decoder for 8-bit RGB, non-interlaced, filter-0 rows."""
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, chunks = 8, b"", []
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])
        assert crc == zlib.crc32(kind + body)
        chunks.append(kind)
        if kind == b"IHDR":
            w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", body)
            assert (depth, ctype, interlace) == (8, 2, 0)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    assert chunks[0] == b"IHDR" and chunks[-1] == b"IEND"
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + 3 * w)
    assert (rows[:, 0] == 0).all()
    return rows[:, 1:].reshape(h, w, 3)


def _listdir(folder):
    return sorted(os.listdir(folder))


# --------------------------------------------------------------------------- EXR


def test_exr_roundtrip_bit_exact(tmp_path):
    rng = np.random.default_rng(0)
    rgb = _random_floats(rng, (17, 23, 3))
    rgb[0, 0] = [np.inf, -np.inf, np.nan]
    rgb[0, 1] = [np.float32(1e-45), -0.0, np.finfo(np.float32).tiny / 2]
    path = tmp_path / "a.exr"
    jio.write_exr(path, rgb)
    back = jio.read_exr(path)
    assert set(back) == {"rgb"}
    assert back["rgb"].dtype == np.float32 and back["rgb"].shape == rgb.shape
    np.testing.assert_array_equal(back["rgb"].view(np.uint32), rgb.view(np.uint32))


def test_exr_accepts_jax_and_float64(tmp_path):
    import jax.numpy as jnp

    rgb = np.random.default_rng(1).random((4, 5, 3))
    jio.write_exr(tmp_path / "j.exr", jnp.asarray(rgb, dtype=jnp.float32))
    jio.write_exr(tmp_path / "d.exr", rgb)
    for name in ("j.exr", "d.exr"):
        np.testing.assert_array_equal(jio.read_exr(tmp_path / name)["rgb"], rgb.astype(np.float32))


def test_exr_aovs_roundtrip(tmp_path):
    rng = np.random.default_rng(2)
    h, w = 6, 9
    image = types.SimpleNamespace(
        rgb=rng.random((h, w, 3), dtype=np.float32),
        depth=rng.random((h, w), dtype=np.float32) * 100,
        normal=rng.standard_normal((h, w, 3)).astype(np.float32),
        albedo=rng.random((h, w, 3), dtype=np.float32),
        steps=rng.integers(0, 256, (h, w)).astype(np.int32),
        coverage=None,  # missing AOVs are skipped
    )
    extra = rng.random((h, w, 2), dtype=np.float32)
    path = tmp_path / "sub" / "dir" / "aov.exr"  # parent folders are created
    jio.write_exr(path, image, channels={"uv": extra})

    with OpenEXR.File(str(path), header_only=True) as f:
        names = {c.name for c in f.header()["channels"]}
    assert names == {"R", "G", "B", "depth.Z", "normal.X", "normal.Y", "normal.Z",
                     "albedo.R", "albedo.G", "albedo.B", "steps.Y", "uv.0", "uv.1"}

    back = jio.read_exr(path)
    assert set(back) == {"rgb", "depth", "normal", "albedo", "steps", "uv"}
    for key in ("rgb", "depth", "normal", "albedo", "uv"):
        np.testing.assert_array_equal(back[key], getattr(image, key, extra))
    np.testing.assert_array_equal(back["steps"], image.steps.astype(np.float32))
    assert back["depth"].shape == (h, w) and back["normal"].shape == (h, w, 3)


@pytest.mark.parametrize(
    "bad, words",
    [
        (np.zeros((4, 5)), "[H, W, 3]"),
        (np.zeros((4, 5, 4)), "[H, W, 3]"),
        (types.SimpleNamespace(rgb=np.zeros((4, 5, 3)), depth=np.zeros((5, 4))), "depth"),
    ],
)
def test_exr_bad_shapes_are_rejected_and_nothing_written(tmp_path, bad, words):
    path = tmp_path / "bad.exr"
    with pytest.raises(ValueError) as e:
        jio.write_exr(path, bad)
    assert str(path) in str(e.value) and words in str(e.value)
    assert _listdir(tmp_path) == []


def test_read_exr_errors_name_the_file(tmp_path):
    missing = tmp_path / "missing.exr"
    with pytest.raises(jio.JaxrtIOError, match="missing.exr.*no such file.*OpenEXR"):
        jio.read_exr(missing)
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an exr file at all")
    with pytest.raises(ValueError, match="junk.exr.*not a readable OpenEXR"):
        jio.read_exr(junk)


# --------------------------------------------------------------------------- atomic writes


def _failing_exr_write(self, path):
    with open(path, "wb") as f:  # write part of a file, then die
        f.write(b"v/1\x01partial")
    raise KeyboardInterrupt("interrupted mid-write")


def test_interrupted_exr_write_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(OpenEXR.File, "write", _failing_exr_write)
    with pytest.raises(KeyboardInterrupt):
        jio.write_exr(tmp_path / "out" / "a.exr", np.ones((3, 3, 3), np.float32))
    assert _listdir(tmp_path / "out") == []


def test_failed_rewrite_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "a.exr"
    old = np.full((3, 4, 3), 0.5, np.float32)
    jio.write_exr(path, old)
    before = path.read_bytes()

    monkeypatch.setattr(OpenEXR.File, "write", _failing_exr_write)
    with pytest.raises(KeyboardInterrupt):
        jio.write_exr(path, np.zeros((3, 4, 3), np.float32))
    monkeypatch.undo()

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    for write in (lambda: jio.write_exr(path, np.zeros((3, 4, 3))),
                  lambda: jio.write_png(path, np.zeros((3, 4, 3)))):
        with pytest.raises(OSError, match="disk full"):
            write()
    monkeypatch.undo()

    assert _listdir(tmp_path) == ["a.exr"]
    assert path.read_bytes() == before
    np.testing.assert_array_equal(jio.read_exr(path)["rgb"], old)


def test_written_files_have_ordinary_permissions(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    jio.write_png(tmp_path / "a.png", np.zeros((2, 2, 3)))
    assert os.stat(tmp_path / "a.png").st_mode & 0o777 == 0o666 & ~umask


# --------------------------------------------------------------------------- PNG


def test_png_matches_colour_science_srgb(tmp_path):
    rng = np.random.default_rng(3)
    rgb = rng.random((7, 11, 3))
    rgb[0, :3] = [0.0, 0.0031308, 1.0]  # the ends and the knee of the OETF
    path = tmp_path / "p.png"
    jio.write_png(path, rgb)
    expected = np.round(255 * colour.models.eotf_inverse_sRGB(rgb)).astype(np.uint8)
    np.testing.assert_array_equal(_decode_png(path), expected)

    try:
        from PIL import Image
    except ImportError:
        return
    with Image.open(path) as im:
        assert im.mode == "RGB"
        np.testing.assert_array_equal(np.asarray(im), expected)


def test_srgb_encode_is_colour_sciences_srgb_oetf():
    """IEC 61966-2-1 as colour-science evaluates it, both branches and the knee."""
    from jaxrt._colour import colour

    x = np.concatenate([np.linspace(0.0, 1.0, 1001), [0.0031308, 0.0031309, 1e-9]])
    ref = colour().cctf_encoding(x, function="sRGB")
    np.testing.assert_allclose(jio.srgb_encode(x), ref, rtol=1e-12, atol=1e-15)


def test_png_exposure_and_clamp(tmp_path):
    a = np.array([[[0.25, 0.1, 0.02], [2.0, -1.0, 0.5]]])
    jio.write_png(tmp_path / "a.png", a, exposure=1.0)
    jio.write_png(tmp_path / "b.png", 2 * a)
    np.testing.assert_array_equal(_decode_png(tmp_path / "a.png"), _decode_png(tmp_path / "b.png"))
    got = _decode_png(tmp_path / "a.png")
    assert got[0, 1].tolist() == [255, 0, 255]  # 4 -> 1, -2 -> 0, 1 -> 1

    jio.write_png(tmp_path / "c.png", np.array([[[np.nan, np.inf, -np.inf]]]), exposure=-3)
    assert _decode_png(tmp_path / "c.png").tolist() == [[[0, 255, 0]]]

    image = types.SimpleNamespace(rgb=a)
    jio.write_png(tmp_path / "d.png", image, exposure=1.0)
    assert (tmp_path / "d.png").read_bytes() == (tmp_path / "a.png").read_bytes()

    with pytest.raises(ValueError, match=r"e.png.*\[H, W, 3\]"):
        jio.write_png(tmp_path / "e.png", np.zeros((2, 2)))


# --------------------------------------------------------------------------- MERL


@pytest.fixture(scope="module")
def merl_file(tmp_path_factory):
    """A MERL file written by hand (independently of write_merl): raw[c, i, j, k] =
    c + i/100 + j/1e4 + k/1e7, so every value says where it came from; one cell is -1."""
    c, i, j, k = np.ix_(np.arange(3), np.arange(90), np.arange(90), np.arange(180))
    raw = c + i / 100 + j / 1e4 + k / 1e7
    raw[:, 5, 6, 7] = -1.0
    path = tmp_path_factory.mktemp("merl") / "tagged.binary"
    path.write_bytes(struct.pack("<3i", 90, 90, 180) + raw.astype("<f8").tobytes())
    return path, raw


def test_read_merl_layout_and_scale(merl_file):
    path, raw = merl_file
    table = jio.read_merl(path)
    assert table.shape == (90, 90, 180, 3) and table.dtype == np.float64
    scale = np.array([1 / 1500, 1.15 / 1500, 1.66 / 1500])
    np.testing.assert_allclose(table[12, 34, 56], (np.arange(3) + 0.12 + 0.0034 + 0.0000056) * scale)
    np.testing.assert_array_equal(table[5, 6, 7], -scale)  # missing data stays negative


def test_merl_roundtrip(tmp_path, merl_file):
    path, _ = merl_file
    table = jio.read_merl(path)
    out = tmp_path / "copy.binary"
    jio.write_merl(out, table)
    np.testing.assert_allclose(jio.read_merl(out), table, rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match=r"small.binary.*\(90, 90, 180, 3\)"):
        jio.write_merl(tmp_path / "small.binary", np.zeros((9, 9, 18, 3)))


def test_merl_rejects_bad_files(tmp_path, merl_file):
    good = merl_file[0].read_bytes()
    cases = {
        "trunc.binary": (good[:-8], r"trunc.binary: truncated.*\d+ bytes, expected 34992012"),
        "header.binary": (good[:5], r"header.binary: truncated.*5 bytes.*header"),
        "dims.binary": (struct.pack("<3i", 90, 90, 360) + good[12:],
                        r"dims.binary.*\(90, 90, 360\), expected \(90, 90, 180\)"),
        "long.binary": (good + b"\0" * 8, r"long.binary: trailing data"),
    }
    for name, (data, pattern) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=pattern):
            jio.read_merl(tmp_path / name)
    with pytest.raises(ValueError, match="nothere.binary"):
        jio.read_merl(tmp_path / "nothere.binary")


def _directions(theta_h, phi_h, theta_d, phi_d):
    """wo, wi from Rusinkiewicz coordinates, built with rotation matrices: wi = Rz(phi_h)
    Ry(theta_h) wd, and wo its mirror about wh."""
    def rz(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    def ry(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    m = rz(phi_h) @ ry(theta_h)
    wd = np.array([np.sin(theta_d) * np.cos(phi_d), np.sin(theta_d) * np.sin(phi_d), np.cos(theta_d)])
    wi, wh = m @ wd, m @ np.array([0.0, 0.0, 1.0])
    return 2 * np.dot(wi, wh) * wh - wi, wi


@pytest.mark.parametrize(
    "angles_deg, cell",
    [
        ((0.0, 0.0, 0.0, 0.0), (0, 0, 0)),
        ((0.0, 0.0, 30.5, 0.0), (0, 30, 0)),  # mirror pair, 30.5 deg off the normal
        ((20.0, 0.0, 40.3, 100.25), (42, 40, 100)),  # floor(sqrt(20 * 90)) = 42
        ((20.0, 73.0, 40.3, 100.25), (42, 40, 100)),  # isotropic: phi_h does not matter
        ((20.0, 73.0, 40.3, -79.75), (42, 40, 100)),  # phi_d + 180 deg: same cell
        ((60.0, -30.0, 10.7, 12.5), (73, 10, 12)),  # floor(sqrt(60 * 90)) = 73
    ],
)
def test_merl_lookup_known_directions(merl_file, angles_deg, cell):
    path, raw = merl_file
    table = jio.read_merl(path)
    wo, wi = _directions(*np.radians(angles_deg))
    assert tuple(int(a) for a in jio.merl_indices(wo, wi)) == cell
    np.testing.assert_array_equal(jio.merl_lookup(table, wo, wi), table[cell])
    np.testing.assert_array_equal(jio.merl_lookup(table, wi, wo), table[cell])  # reciprocity


def test_merl_angles_are_cell_centres():
    theta_h, theta_d, phi_d = jio.merl_angles()
    assert theta_h.shape == theta_d.shape == phi_d.shape == (90, 90, 180)
    rng = np.random.default_rng(4)
    idx = tuple(rng.integers(0, n, 2000) for n in (90, 90, 180))
    angles = (theta_h[idx], theta_d[idx], phi_d[idx])
    for n in range(2000):
        th, td, pd = (a[n] for a in angles)
        wo, wi = _directions(th, rng.uniform(-np.pi, np.pi), td, pd)
        got = tuple(int(a) for a in jio.merl_indices(wo, wi))
        assert got == (idx[0][n], idx[1][n], idx[2][n])


def test_merl_lookup_batches_and_horizon():
    table = np.random.default_rng(5).random((90, 90, 180, 3))
    wo = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.6, 0.0, -0.8]])
    wi = np.array([[0.0, 0.0, 1.0], [-0.6, 0.0, 0.8], [0.0, 0.0, 1.0]])
    f = jio.merl_lookup(table, wo, wi)
    assert f.shape == (3, 3)
    np.testing.assert_array_equal(f[0], table[0, 0, 0])
    np.testing.assert_array_equal(f[2], 0.0)  # below the horizon
