"""Reading and writing images and measured BRDFs.

- EXR (OpenEXR): linear float32 radiance plus AOV layers; lossless round trip.
- PNG: an 8-bit sRGB-encoded preview of linear radiance (the sRGB OETF of IEC 61966-2-1,
  in numpy), written with the standard library (zlib + struct).
- MERL: the binary BRDF tables of Matusik et al. 2003, "A Data-Driven Reflectance Model",
  used by the BRDF-fitting study (Ngan et al. 2005).

Every writer writes a temporary file in the target's folder and renames it over the
target (`os.replace`, atomic on POSIX), so an interrupted or failed write leaves either
the old file or no file, never a truncated one. `write_render` writes a render's EXR and
PNG all or nothing: both go to temporary names and are renamed only when both were
written. `check_writable` tells, before any work, whether a file can be created at a
path. Every reader and writer raises `JaxrtIOError` (a `ValueError`) naming the file,
what it found and what it expected.
"""

from __future__ import annotations

import os
import struct
import tempfile
import zlib
from collections.abc import Callable, Mapping

import numpy as np
import OpenEXR


class JaxrtIOError(ValueError):
    """A file could not be read or written: the message names the file and the problem."""


# --------------------------------------------------------------------------- atomic write


def _umask() -> int:
    # Read without changing it (os.umask would, racily, in threaded programs).
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    return 0o022


def _atomic_write(path, write: Callable[[str], None]) -> None:
    """Call `write(tmp_path)` on a temporary file beside `path`, then rename it to `path`.

    On any exception (KeyboardInterrupt included) the temporary file is removed and an
    existing `path` is left untouched.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    # Hidden name, so globs for the final files never see a partial one.
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{os.path.basename(path)}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        # mkstemp creates 0600; give the file the mode an ordinary create would have.
        mode = os.stat(path).st_mode & 0o777 if os.path.exists(path) else 0o666 & ~_umask()
        os.chmod(tmp, mode)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)  # the data is on disk before the name points at it
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.remove(tmp)
        except FileNotFoundError:
            pass
        raise


def _existing_folder(path) -> str:
    """The nearest folder of `path` that exists (its parent, or an ancestor of it)."""
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    while not os.path.exists(folder):
        folder = os.path.dirname(folder)
    return folder


def check_writable(path) -> None:
    """Raise `JaxrtIOError` unless a file can be written at `path` now.

    `path` must not be a folder; its nearest existing ancestor must be a folder in which
    a file can be created (tried: a hidden temporary file is created and removed, so the
    answer holds for root, read-only mounts and ACLs alike). Missing folders below it
    would be created by the writers.
    """
    spath = os.fspath(path)
    if os.path.isdir(spath):
        raise JaxrtIOError(f"{spath}: is a folder, expected a file name to write")
    folder = _existing_folder(spath)
    if not os.path.isdir(folder):
        raise JaxrtIOError(f"{spath}: cannot write, {folder} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".jaxrt-probe.", suffix=".tmp")
    except OSError as e:
        raise JaxrtIOError(f"{spath}: cannot write in {folder} ({e.strerror or e})") from None
    os.close(fd)
    os.remove(probe)


def write_render(exr_path, png_path, image, exposure: float = 0.0) -> None:
    """Write a render's EXR (`write_exr`, with its AOVs) and PNG preview (`write_png`),
    all or nothing.

    Both are written to hidden temporary names beside their targets and renamed only when
    both were written; on any failure (an `OSError`, a `JaxrtIOError`, an interrupt) the
    temporary files, a target already renamed and the folders this call created are
    removed again, and the error is raised as a `JaxrtIOError` naming the file. (A target
    that existed before is replaced only when both new files are in place.)
    """
    targets = [os.fspath(exr_path), os.fspath(png_path)]
    for target in targets:
        check_writable(target)
    created, temps, done = [], [], []
    current = targets[0]
    try:
        for target in targets:
            current = target
            folder = os.path.dirname(os.path.abspath(target))
            missing = []
            while not os.path.exists(folder):
                missing.append(folder)
                folder = os.path.dirname(folder)
            for f in reversed(missing):
                os.mkdir(f)
                created.append(f)
            fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(target)),
                                       prefix=f".{os.path.basename(target)}.", suffix=".tmp")
            os.close(fd)
            temps.append(tmp)
        current = targets[0]
        write_exr(temps[0], image)
        current = targets[1]
        write_png(temps[1], getattr(image, "rgb", image), exposure=exposure)
        for tmp, target in zip(temps, targets):
            current = target
            os.replace(tmp, target)
            done.append(target)
    except BaseException as e:
        for f in temps + done:
            try:
                os.remove(f)
            except OSError:
                pass
        for f in reversed(created):
            try:
                os.rmdir(f)
            except OSError:
                pass
        if isinstance(e, JaxrtIOError):
            message = str(e)
            for tmp, target in zip(temps, targets):
                message = message.replace(tmp, target)
            raise JaxrtIOError(message) from None
        if isinstance(e, OSError):
            raise JaxrtIOError(f"{current}: cannot write ({e.strerror or e})") from None
        raise


# --------------------------------------------------------------------------- EXR

# Channel suffixes of the known AOV layers; any other [H,W] array is written as
# `name.Y`, any other [H,W,3] as `name.R/G/B`.
_AOV_SUFFIXES = {
    "depth": ("Z",),
    "normal": ("X", "Y", "Z"),
    "albedo": ("R", "G", "B"),
    "steps": ("Y",),
    "coverage": ("Y",),
}
# Order in which `read_exr` stacks a layer's channels; unknown suffixes follow, sorted.
_SUFFIX_ORDER = ("R", "G", "B", "A", "X", "Y", "Z", "U", "V", "W")


def _suffixes(name: str, n: int) -> tuple[str, ...]:
    if name in _AOV_SUFFIXES and len(_AOV_SUFFIXES[name]) == n:
        return _AOV_SUFFIXES[name]
    if n == 1:
        return ("Y",)
    if n in (3, 4):
        return ("R", "G", "B", "A")[:n]
    return tuple(str(i) for i in range(n))


def _layer_channels(path, name: str, array, hw: tuple[int, int]) -> dict[str, np.ndarray]:
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[:2] != hw:
        raise JaxrtIOError(
            f"{path}: AOV `{name}` has shape {np.shape(array)}, expected [{hw[0]}, {hw[1]}] "
            f"or [{hw[0]}, {hw[1]}, C] to match rgb"
        )
    return {
        f"{name}.{s}": np.ascontiguousarray(a[..., i], dtype=np.float32)
        for i, s in enumerate(_suffixes(name, a.shape[-1]))
    }


def write_exr(path, image_or_array, channels: Mapping[str, object] | None = None) -> None:
    """Write linear radiance, and any AOVs, to an OpenEXR file as float32 (ZIP, lossless).

    **Arguments:**

    - `path`: the target file; parent folders are created. Written atomically.
    - `image_or_array`: an [H, W, 3] array (numpy or jax) of linear RGB, written as
      channels `R, G, B`; or an object with `.rgb` ([H, W, 3]) and optional AOV
      attributes `depth` [H, W] (`depth.Z`), `normal` [H, W, 3] (`normal.X/Y/Z`),
      `albedo` [H, W, 3] (`albedo.R/G/B`), `steps` [H, W] (`steps.Y`) and `coverage`
      [H, W] (`coverage.Y`); attributes that are missing or `None` are skipped.
    - `channels`: extra layers, name -> [H, W] or [H, W, C] array, named as above
      ([H, W] -> `name.Y`, [H, W, 3] -> `name.R/G/B`).

    Values are cast to float32 (float64 input loses precision; float32 is kept bit for bit,
    inf and NaN included).
    """
    has_aovs = hasattr(image_or_array, "rgb")
    rgb = np.asarray(image_or_array.rgb if has_aovs else image_or_array)
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise JaxrtIOError(f"{path}: rgb has shape {rgb.shape}, expected [H, W, 3] with H, W > 0")
    hw = rgb.shape[:2]
    pixels = {c: np.ascontiguousarray(rgb[..., i], dtype=np.float32) for i, c in enumerate("RGB")}
    layers = {}
    if has_aovs:
        for name in _AOV_SUFFIXES:
            value = getattr(image_or_array, name, None)
            if value is not None:
                layers[name] = value
    layers.update(channels or {})
    for name, value in layers.items():
        pixels.update(_layer_channels(path, name, value, hw))
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: str) -> None:
        with OpenEXR.File(header, pixels) as f:
            f.write(tmp)

    _atomic_write(path, write)


def read_exr(path) -> dict[str, np.ndarray]:
    """Read an OpenEXR file into float32 arrays grouped by layer.

    Channels `R, G, B` become `"rgb"` [H, W, 3]. A layer `name.S` with one channel becomes
    `name` [H, W]; with several, `name` [H, W, C], channels in the order R G B A X Y Z
    (then the rest, sorted): `"normal"` is [H, W, 3] in X, Y, Z order, `"depth"` [H, W].
    Other channels without a layer prefix keep their own name (`"A"`, `"Z"`, ...).
    """
    spath = os.fspath(path)
    if not os.path.isfile(spath):
        raise JaxrtIOError(f"{spath}: no such file, expected an OpenEXR image")
    try:
        with OpenEXR.File(spath, separate_channels=True) as f:
            raw = {name: np.asarray(c.pixels, dtype=np.float32) for name, c in f.channels().items()}
    except Exception as e:  # OpenEXR raises RuntimeError for anything unreadable
        raise JaxrtIOError(f"{spath}: not a readable OpenEXR image ({e})") from None

    groups: dict[str, dict[str, np.ndarray]] = {}
    out: dict[str, np.ndarray] = {}
    for name, a in raw.items():
        layer, dot, suffix = name.rpartition(".")
        if dot:
            groups.setdefault(layer, {})[suffix] = a
        elif name in ("R", "G", "B") and all(c in raw for c in "RGB"):
            groups.setdefault("rgb", {})[name] = a
        else:
            out[name] = a
    for layer, chans in groups.items():
        order = sorted(chans, key=lambda s: (_SUFFIX_ORDER.index(s) if s in _SUFFIX_ORDER
                                             else len(_SUFFIX_ORDER), s))
        out[layer] = chans[order[0]] if len(order) == 1 else np.stack([chans[s] for s in order], -1)
    return out


# --------------------------------------------------------------------------- PNG


def srgb_encode(x) -> np.ndarray:
    """The sRGB OETF (IEC 61966-2-1): 12.92 x for x <= 0.0031308, else 1.055 x^(1/2.4) - 0.055.

    Float64, in numpy: colour-science (`colour.cctf_encoding(x, function="sRGB")`, which
    tests/test_io.py compares against) takes over a second to import, a fifth of a
    warm `jaxrt render`.
    """
    x = np.asarray(x, dtype=np.float64)
    high = 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055
    return np.where(x <= 0.0031308, 12.92 * x, high)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_bytes(rgb8: np.ndarray) -> bytes:
    """Encode an [H, W, 3] uint8 array as an 8-bit RGB PNG (every row filter 0)."""
    h, w, _ = rgb8.shape
    rows = np.concatenate([np.zeros((h, 1), np.uint8), rgb8.reshape(h, 3 * w)], axis=1)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
        + _png_chunk(b"sRGB", b"\x00")  # perceptual rendering intent: the data is sRGB
        + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + _png_chunk(b"IEND", b"")
    )


def write_png(path, rgb, exposure: float = 0.0) -> None:
    """Write an 8-bit sRGB preview of linear radiance.

    Each value becomes round(255 * srgb_encode(clip(x * 2**exposure, 0, 1))). NaN is
    written as 0 and +inf as 1 (so a broken pixel is visible, not a failed preview).

    **Arguments:**

    - `path`: the target PNG file; parent folders are created. Written atomically.
    - `rgb`: [H, W, 3] linear RGB (numpy or jax), or an object with `.rgb`.
    - `exposure`: in stops; the radiance is scaled by 2**exposure before clamping.
    """
    x = np.asarray(getattr(rgb, "rgb", rgb), dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] == 0 or x.shape[1] == 0:
        raise JaxrtIOError(f"{path}: rgb has shape {x.shape}, expected [H, W, 3] with H, W > 0")
    x = np.nan_to_num(x * 2.0 ** float(exposure), nan=0.0, posinf=1.0, neginf=0.0)
    rgb8 = np.round(255.0 * srgb_encode(np.clip(x, 0.0, 1.0))).astype(np.uint8)
    data = _png_bytes(rgb8)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    _atomic_write(path, write)


# --------------------------------------------------------------------------- MERL BRDF

MERL_SHAPE = (90, 90, 180)  # theta_half, theta_diff, phi_diff
MERL_SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])  # R, G, B
_MERL_HEADER = 3 * 4
_MERL_SIZE = _MERL_HEADER + 3 * int(np.prod(MERL_SHAPE)) * 8


def read_merl(path) -> np.ndarray:
    """Read a MERL BRDF file into a [90, 90, 180, 3] float64 table of linear RGB f_r (1/sr).

    Axes are (theta_half, theta_diff, phi_diff) in Rusinkiewicz's half/difference
    coordinates; see `merl_angles` for the angle of each cell. The file is three
    little-endian int32 dimensions (90, 90, 180), then 3 x 90*90*180 float64 values,
    all red, then all green, then all blue; each channel is multiplied by MERL's scale
    (R 1/1500, G 1.15/1500, B 1.66/1500).

    Negative values mark cells where MERL has no measurement. They are kept as they are
    (after scaling): mask them, `table >= 0`, before fitting or averaging.
    """
    spath = os.fspath(path)
    try:
        with open(spath, "rb") as f:
            data = f.read()
    except OSError as e:
        raise JaxrtIOError(f"{spath}: cannot read MERL BRDF file ({e.strerror})") from None
    if len(data) < _MERL_HEADER:
        raise JaxrtIOError(
            f"{spath}: truncated MERL BRDF file: {len(data)} bytes, expected a 12-byte header "
            f"(three int32 dimensions) and {_MERL_SIZE} bytes in all"
        )
    dims = struct.unpack("<3i", data[:_MERL_HEADER])
    if dims != MERL_SHAPE:
        raise JaxrtIOError(
            f"{spath}: MERL BRDF dimensions are {dims}, expected {MERL_SHAPE} "
            "(theta_half, theta_diff, phi_diff)"
        )
    if len(data) != _MERL_SIZE:
        what = "truncated" if len(data) < _MERL_SIZE else "trailing data in"
        raise JaxrtIOError(
            f"{spath}: {what} MERL BRDF file: {len(data)} bytes, expected {_MERL_SIZE} "
            f"(12-byte header + 3 x {'x'.join(map(str, MERL_SHAPE))} float64)"
        )
    values = np.frombuffer(data, dtype="<f8", offset=_MERL_HEADER).reshape(3, *MERL_SHAPE)
    return np.moveaxis(values, 0, -1) * MERL_SCALE


def write_merl(path, table) -> None:
    """Write a [90, 90, 180, 3] table of linear RGB f_r as a MERL BRDF file (inverse of
    `read_merl`, scale factors divided out). Written atomically."""
    t = np.asarray(table, dtype=np.float64)
    if t.shape != (*MERL_SHAPE, 3):
        raise JaxrtIOError(f"{path}: MERL table has shape {t.shape}, expected {(*MERL_SHAPE, 3)}")
    data = struct.pack("<3i", *MERL_SHAPE) + np.moveaxis(t / MERL_SCALE, -1, 0).astype("<f8").tobytes()

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    _atomic_write(path, write)


def merl_angles() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_h, theta_d, phi_d) in radians at every cell centre, each [90, 90, 180].

    MERL's index mapping is i = floor(sqrt(theta_h / (pi/2)) * 90), j = floor(theta_d /
    (pi/2) * 90), k = floor(phi_d / pi * 180); the centre of cell (i, j, k) is the angle
    at index + 0.5: theta_h = ((i + 0.5) / 90)^2 pi/2 (dense near the highlight),
    theta_d = (j + 0.5) / 90 pi/2, phi_d = (k + 0.5) / 180 pi.
    """
    i, j, k = (np.arange(n) + 0.5 for n in MERL_SHAPE)
    theta_h = (i / 90.0) ** 2 * (np.pi / 2)
    theta_d = j / 90.0 * (np.pi / 2)
    phi_d = k / 180.0 * np.pi
    return tuple(np.broadcast_arrays(*np.ix_(theta_h, theta_d, phi_d)))


def _normalize(v, xp=np):
    # The floor keeps wo = −wi (a pair below the horizon) finite.
    return v / xp.maximum(xp.linalg.norm(v, axis=-1, keepdims=True), 1e-30)


def half_diff_angles(wo, wi, xp=np) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rusinkiewicz (1998) coordinates (theta_h, theta_d, phi_d) of [..., 3] local-frame
    directions (normal +z, both pointing away from the surface).

    wh = normalize(wo + wi); wd is wi rotated by -phi_h about z, then by -theta_h about y
    (so wh goes to +z); theta_d, phi_d are wd's polar angles, phi_d in (-pi, pi].
    `xp`: the array module, numpy (float64, default) or jax.numpy (traceable; used by
    `jaxrt.fit_brdf.TabulatedBRDF`).
    """
    dtype = np.float64 if xp is np else float
    wo, wi = _normalize(xp.asarray(wo, dtype), xp), _normalize(xp.asarray(wi, dtype), xp)
    wh = _normalize(wo + wi, xp)
    theta_h = xp.arccos(xp.clip(wh[..., 2], -1.0, 1.0))
    phi_h = xp.arctan2(wh[..., 1], wh[..., 0])
    c, s = xp.cos(phi_h), xp.sin(phi_h)
    x = c * wi[..., 0] + s * wi[..., 1]
    y = -s * wi[..., 0] + c * wi[..., 1]
    z = wi[..., 2]
    ct, st = xp.cos(theta_h), xp.sin(theta_h)
    x, z = ct * x - st * z, st * x + ct * z
    return theta_h, xp.arccos(xp.clip(z, -1.0, 1.0)), xp.arctan2(y, x)


def merl_indices(wo, wi, xp=np) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Table indices (i, j, k) for [..., 3] direction pairs, as in MERL's BRDFRead.cpp:
    i = floor(sqrt(theta_h / (pi/2) * 90 * 90)), j = floor(theta_d / (pi/2) * 90),
    k = floor((phi_d mod pi) / pi * 180), since reciprocity makes f_r(phi_d) =
    f_r(phi_d + pi); each clamped to the table. (BRDFRead.cpp adds pi to negative phi_d
    and clamps, so at phi_d = +pi exactly it picks k = 179 where this picks k = 0: the same
    angle, and a swap of wo and wi no longer changes the cell.) `xp` as for
    `half_diff_angles`."""
    theta_h, theta_d, phi_d = half_diff_angles(wo, wi, xp)
    i = xp.sqrt(xp.maximum(theta_h, 0.0) / (np.pi / 2) * 90.0 * 90.0)
    j = theta_d / (np.pi / 2) * 90.0
    k = xp.mod(phi_d, np.pi) / np.pi * 180.0
    index = np.int64 if xp is np else xp.int32
    return tuple(xp.clip(xp.floor(a).astype(index), 0, n - 1) for a, n in zip((i, j, k), MERL_SHAPE))


def merl_lookup(table, wo, wi) -> np.ndarray:
    """f_r (RGB, [..., 3]) from a MERL table for [..., 3] local-frame directions, by
    nearest cell (no interpolation). Pairs with either direction at or below the horizon
    get 0. Missing-data cells stay negative, as in the table."""
    table = np.asarray(table)
    i, j, k = merl_indices(wo, wi)
    above = (np.asarray(wo)[..., 2] > 0) & (np.asarray(wi)[..., 2] > 0)
    return np.where(above[..., None], table[i, j, k], 0.0)
