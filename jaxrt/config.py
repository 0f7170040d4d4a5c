"""TOML scene files → (Scene, Camera, RenderSettings), with errors that name the key.

A scene file has the tables

    [camera]      type = "perspective" | "orthographic", and the camera's arguments
    [settings]    any `RenderSettings` field (optional)
    [materials.NAME]  type = a `jaxrt.bsdf` material in snake_case ("lambert",
                  "cook_torrance", ...) and its arguments; NAME is how shapes refer to
                  it (`material = "NAME"`), in the order of the file
    [[lights]]    type = "point" | "directional", and the light's arguments
    [[heightfields]]  height fields y = h(x, z) (optional): `height` is a table with
                  type = "plane" | "sine" | "grid" and its arguments (a grid's
                  `heights` is an array of rows, or the path of a .npy file relative
                  to the scene file), `material` a material name, and the other
                  `jaxrt.heightfield.HeightField` arguments (max_steps, min_step, ...)
    [surface]     a shape tree: `type` is a `jaxrt.sdf` node in snake_case ("sphere",
                  "smooth_union", "translate", ...); combinations take `children`
                  (union, intersection) or `a` and `b`; placements and deformations
                  take `child`; a "grid" (`jaxrt.sdf.Grid`) takes `values`, an
                  [nx, ny, nz] nested array or the path of a .npy file relative to the
                  scene file, and the box's `lower` and `upper` corners
    background = [r, g, b]   (top level, optional)

Every error is a `ConfigError` whose message reads
`FILE: KEY.PATH = VALUE, expected WHAT`; nothing from inside JAX reaches the user.
"""

import dataclasses
import inspect
import re
import tomllib
from pathlib import Path

import numpy as np

from . import bsdf, sdf
from .heightfield import GridHeight, HeightField, PlaneHeight, SineHeight
from .bsdf.base import Material
from .camera import OrthographicCamera, PerspectiveCamera
from .lights import DirectionalLight, PointLight
from .scene import Scene
from .settings import RenderSettings


class ConfigError(ValueError):
    """A scene file that cannot be loaded; the message names the file and the key."""


def _snake(name):
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name).lower()


#: Shape nodes by their config name.
SHAPES = {
    _snake(name): cls
    for name, cls in vars(sdf).items()
    if isinstance(cls, type) and issubclass(cls, sdf.SDF) and cls not in (sdf.SDF, sdf.Primitive)
}
#: Materials by their config name.
MATERIALS = {
    _snake(name): cls
    for name, cls in vars(bsdf).items()
    if isinstance(cls, type) and issubclass(cls, Material) and not inspect.isabstract(cls)
}
LIGHTS = {"point": PointLight, "directional": DirectionalLight}
HEIGHTS = {"plane": PlaneHeight, "sine": SineHeight, "grid": GridHeight}
CAMERAS = {"perspective": PerspectiveCamera, "orthographic": OrthographicCamera}
#: Parts given as nested tables with a `type` (`distribution = {type = "ggx", alpha = 0.2}`).
PARTS = {"sine_displacement": sdf.SineDisplacement} | {
    _snake(name): cls
    for name, cls in vars(bsdf).items()
    if isinstance(cls, type) and not issubclass(cls, Material) and hasattr(cls, "__call__")
    and hasattr(cls, "__dataclass_fields__") and not inspect.isabstract(cls)
}

#: Value ranges checked before construction: argument name → (test, expectation).
_POSITIVE = (lambda v: np.all(v > 0), "> 0")
_NONNEGATIVE = (lambda v: np.all(v >= 0), "≥ 0")
RANGES = {
    "radius": _POSITIVE, "half_extents": _POSITIVE, "major_radius": _POSITIVE,
    "minor_radius": _POSITIVE, "height": _POSITIVE, "half_height": _POSITIVE,
    "radii": _POSITIVE, "factor": _POSITIVE, "size": _POSITIVE,
    "fov": (lambda v: np.all((v > 0) & (v < 180)), "in (0, 180) degrees"),
    "k": _NONNEGATIVE, "period": _NONNEGATIVE, "albedo": _NONNEGATIVE,
    "intensity": _NONNEGATIVE, "irradiance": _NONNEGATIVE, "eta": _POSITIVE,
    "alpha": _POSITIVE, "roughness": _POSITIVE, "exponent": _NONNEGATIVE,
    "background": _NONNEGATIVE,
}

SDF_OR_INDEX = (sdf.SDF,)
_TOP_KEYS = {"camera", "settings", "materials", "lights", "surface", "background", "heightfields"}


def load(path, *, width=None, height=None, spp=None, settings=None):
    """Load a scene file. Returns `(scene, camera, settings)`.

    `width`, `height` and `spp` override the file's values (command-line use);
    `settings`, a {field: value} table like the file's [settings], overrides its fields.
    Raises `ConfigError` naming the file, the key path and what was expected.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the file ({e.strerror or e})") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: malformed TOML: {e}") from None
    if settings:
        table = doc.get("settings", {})
        doc["settings"] = {**table, **settings} if isinstance(table, dict) else table
    return _Loader(str(path), path.parent).load(doc, width=width, height=height, spp=spp)


def check_settings(table, name="<settings>"):
    """`RenderSettings` from a [settings]-like table, checked as a file's are; `name`
    stands for the file in messages (`--set: settings.max_steps = 0, expected ...`)."""
    return _Loader(name, Path.cwd()).settings(table, None)


def loads(text, name="<string>", **overrides):
    """Like `load`, from TOML text; `name` stands for the file in messages."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{name}: malformed TOML: {e}") from None
    return _Loader(name, Path.cwd()).load(doc, **overrides)


class _Loader:
    def __init__(self, name, folder):
        self.name = name
        self.folder = folder  # where relative paths in the file start

    def fail(self, key, value, expected):
        shown = _show(value)
        raise ConfigError(f"{self.name}: {key} = {shown}, expected {expected}")

    def fail_missing(self, key, expected):
        raise ConfigError(f"{self.name}: {key} is missing, expected {expected}")

    # -- top level ----------------------------------------------------------------

    def load(self, doc, width=None, height=None, spp=None):
        for key in doc:
            if key not in _TOP_KEYS:
                self.fail(key, doc[key], f"one of the tables {sorted(_TOP_KEYS)} (unknown key)")
        settings = self.settings(doc.get("settings", {}), spp)
        materials, names = self.materials(doc.get("materials"))
        surface = self.shape(self.table(doc, "surface"), "surface", names)
        lights = [self.light(l, f"lights[{i}]") for i, l in enumerate(self.list(doc, "lights"))]
        fields = [self.heightfield(h, f"heightfields[{i}]", names)
                  for i, h in enumerate(self.list(doc, "heightfields"))]
        camera = self.camera(self.table(doc, "camera"), width, height)
        background = (0.0, 0.0, 0.0)
        if "background" in doc:
            background = self.value("background", doc["background"], (0.0, 0.0, 0.0), "background")
        try:
            scene = Scene(surface=surface, materials=materials, lights=lights, background=background,
                          heightfields=fields)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{self.name}: {e}") from None
        return scene, camera, settings

    def table(self, doc, key):
        if key not in doc:
            self.fail_missing(key, "a table")
        if not isinstance(doc[key], dict):
            self.fail(key, doc[key], "a table")
        return doc[key]

    def list(self, doc, key):
        value = doc.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            self.fail(key, value, f"an array of tables ([[{key}]])")
        return value

    # -- parts --------------------------------------------------------------------

    def settings(self, table, spp):
        if not isinstance(table, dict):
            self.fail("settings", table, "a table")
        fields = {f.name for f in dataclasses.fields(RenderSettings)}
        for key in table:
            if key not in fields:
                self.fail(f"settings.{key}", table[key], f"a RenderSettings field, one of {sorted(fields)}")
        values = dict(table)
        if spp is not None:
            values["spp"] = spp
        try:
            return RenderSettings(**values)
        except ValueError as e:
            m = re.match(r"RenderSettings\.([\w.]+) = (.*), expected (.*)", str(e))
            if m:
                raise ConfigError(f"{self.name}: settings.{m[1]} = {m[2]}, expected {m[3]}") from None
            raise ConfigError(f"{self.name}: settings: {e}") from None

    def materials(self, table):
        if table is None:
            self.fail_missing("materials", "at least one [materials.NAME] table")
        if not isinstance(table, dict) or not table:
            self.fail("materials", table, "at least one [materials.NAME] table")
        out, names = [], {}
        for i, (name, spec) in enumerate(table.items()):
            key = f"materials.{name}"
            if not isinstance(spec, dict):
                self.fail(key, spec, "a table with a `type`")
            out.append(self.build(spec, key, MATERIALS, "material"))
            names[name] = i
        return out, names

    def light(self, spec, key):
        return self.build(spec, key, LIGHTS, "light")

    def camera(self, spec, width, height):
        spec = dict(spec)
        spec.setdefault("type", "perspective")
        if width is not None:
            spec["width"] = width
        if height is not None:
            spec["height"] = height
        return self.build(spec, "camera", CAMERAS, "camera")

    def shape(self, spec, key, names):
        if not isinstance(spec, dict):
            self.fail(key, spec, "a shape table with a `type`")
        cls = self.kind(spec, key, SHAPES, "shape")
        args = {}
        for arg, value in spec.items():
            if arg == "type":
                continue
            sub = f"{key}.{arg}"
            if arg == "children" and cls in (sdf.Union, sdf.Intersection):
                if not isinstance(value, list) or not value:
                    self.fail(sub, value, "a non-empty array of shape tables")
                args[arg] = [self.shape(c, f"{sub}[{i}]", names) for i, c in enumerate(value)]
            elif arg in ("child", "a", "b"):
                args[arg] = self.shape(value, sub, names)
            elif arg == "material":
                args[arg] = self.material_ref(value, sub, names)
            elif arg == "values" and cls is sdf.Grid and isinstance(value, str):
                args[arg] = self.array_file(value, sub)
                if not np.all(np.isfinite(args[arg])):
                    self.fail(sub, value, "a .npy file of finite numbers (it has NaN or inf)")
            else:
                args[arg] = value
        if cls in (sdf.Union, sdf.Intersection):
            if "children" not in args:
                self.fail_missing(f"{key}.children", "a non-empty array of shape tables")
            children = args.pop("children")
            self.check_args(cls, args, key, varargs=True)
            return self.construct(lambda: cls(*children, **args), key)
        return self.construct_checked(cls, args, key)

    def heightfield(self, spec, key, names):
        if not isinstance(spec, dict):
            self.fail(key, spec, "a height-field table with a `height` table")
        args = dict(spec)
        if "height" not in args:
            self.fail_missing(f"{key}.height", f"a table with a type, one of {sorted(HEIGHTS)}")
        height = dict(args.pop("height")) if isinstance(args["height"], dict) else args.pop("height")
        if isinstance(height, dict) and isinstance(height.get("heights"), str):
            height["heights"] = self.array_file(height["heights"], f"{key}.height.heights")
        height = self.build(height, f"{key}.height", HEIGHTS, "height")
        if "material" in args:
            args["material"] = self.material_ref(args["material"], f"{key}.material", names)
        params = self.check_args(HeightField, args, key)
        for arg, value in args.items():
            if arg != "material":
                args[arg] = self.value(f"{key}.{arg}", value, params[arg].default, arg)
        return self.construct(lambda: HeightField(height, **args), key)

    def array_file(self, name, key):
        """A .npy file named relative to the scene file."""
        path = self.folder / name
        if path.suffix != ".npy":
            self.fail(key, name, "an array of rows or the path of a .npy file")
        try:
            return np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            self.fail(key, name, f"a readable .npy file ({e})")

    def material_ref(self, value, key, names):
        if isinstance(value, str):
            if value not in names:
                self.fail(key, value, f"the name of a [materials.NAME] table, one of {sorted(names)}")
            return names[value]
        if isinstance(value, int) and not isinstance(value, bool):
            if not 0 <= value < len(names):
                self.fail(key, value, f"a material index in 0..{len(names) - 1}")
            return value
        self.fail(key, value, "a material name (string) or index")

    # -- generic construction -----------------------------------------------------

    def kind(self, spec, key, registry, what):
        if "type" not in spec:
            self.fail_missing(f"{key}.type", f"a {what} type, one of {sorted(registry)}")
        name = spec["type"]
        if not isinstance(name, str) or name not in registry:
            self.fail(f"{key}.type", name, f"a {what} type, one of {sorted(registry)}")
        return registry[name]

    def build(self, spec, key, registry, what):
        if not isinstance(spec, dict):
            self.fail(key, spec, f"a {what} table with a `type`")
        cls = self.kind(spec, key, registry, what)
        args = {k: v for k, v in spec.items() if k != "type"}
        return self.construct_checked(cls, args, key)

    def check_args(self, cls, args, key, varargs=False):
        params = _parameters(cls)
        for arg, value in args.items():
            if arg not in params:
                allowed = sorted(params) + (["children"] if varargs else [])
                self.fail(f"{key}.{arg}", value, f"one of the arguments {allowed} (unknown key)")
        return params

    def construct_checked(self, cls, args, key):
        params = self.check_args(cls, args, key)
        for arg, value in args.items():
            if isinstance(value, dict):
                args[arg] = self.build(value, f"{key}.{arg}", PARTS, "part")
            elif not isinstance(value, SDF_OR_INDEX):
                args[arg] = self.value(f"{key}.{arg}", value, params[arg].default, arg)
        for name, p in params.items():
            if p.default is inspect.Parameter.empty and name not in args:
                self.fail_missing(f"{key}.{name}", "a value")
        return self.construct(lambda: cls(**args), key)

    def value(self, key, value, default, arg):
        """Type- and range-check one argument against its default's kind."""
        if isinstance(default, bool):
            if not isinstance(value, bool):
                self.fail(key, value, "true or false")
            return value
        if isinstance(default, str):
            if not isinstance(value, str):
                self.fail(key, value, "a string")
            return value
        if isinstance(default, int) and arg in ("width", "height"):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                self.fail(key, value, "an integer ≥ 1")
            return value
        if value is None or isinstance(value, (str, bool, dict)):
            self.fail(key, value, _expected_numbers(default))
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            self.fail(key, value, _expected_numbers(default))
        if not np.all(np.isfinite(array)):
            self.fail(key, value, "finite numbers")
        if arg in RANGES:
            test, expected = RANGES[arg]
            if not test(array):
                self.fail(key, value, f"a value {expected}")
        return value

    def construct(self, make, key):
        try:
            return make()
        except ConfigError:
            raise
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{self.name}: {key}: {e}") from None


def _parameters(cls):
    sig = inspect.signature(cls.__init__)
    return {
        n: p for n, p in sig.parameters.items()
        if n != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
    }


def _expected_numbers(default):
    if default is inspect.Parameter.empty or default is None:
        return "a number or an array of numbers"
    n = np.size(default)
    return "a number" if np.ndim(default) == 0 else f"{n} numbers (or one number for all)"


def _show(value):
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, dict):
        return "{...}"
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value)
