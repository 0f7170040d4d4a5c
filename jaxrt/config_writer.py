"""Scene, camera and settings → a TOML scene file that `jaxrt.config.load` reads back
(the inverse of the loader, for fitted scenes).

Each node is written as its config `type` (the loader's registries, `jaxrt.config`)
and its constructor arguments, read from the fields of the same name: shape trees as
nested tables (`[surface]`, `[[surface.children]]`, `[surface.child]`), materials as
`[materials.m<i>]` referred to by name, lights as `[[lights]]`, height fields as
`[[heightfields]]` (grid heights inline). Floats are written with repr (round trip
exact). A dispersive `Dielectric` (a `jaxrt.spectral` index model, which scene files
only name by preset) is written with its index at the reference wavelength and the
model in a comment.
"""

import dataclasses
import math

import equinox as eqx
import numpy as np

from . import config
from .bsdf.specular import REFERENCE_WAVELENGTH_NM, Dielectric
from .settings import RenderSettings

__all__ = ["dumps", "dump"]

# Field names that differ from the constructor argument they hold.
_FIELD = {"lipschitz": "displacement_lipschitz"}


def _type_name(obj, registry):
    for name, cls in registry.items():
        if type(obj) is cls:
            return name
    raise ValueError(f"`jaxrt.config_writer`: {type(obj).__name__} has no scene-file type")


def _value(x):
    if isinstance(x, (bool, str, int)) and not isinstance(x, np.integer):
        return x
    a = np.asarray(x)
    if a.dtype.kind in "iu":
        return a.tolist()
    return np.asarray(a, float).tolist()


def _node(obj, registry, comments):
    """A dict for one node: its `type` and arguments (nested nodes as dicts)."""
    out = {"type": _type_name(obj, registry)}
    cls = type(obj)
    if cls in (config.sdf.Union, config.sdf.Intersection):  # constructed from *children
        out["children"] = [_node(c, config.SHAPES, comments) for c in obj.children()]
    for name, p in config._parameters(cls).items():
        field = _FIELD.get(name, name)
        if not hasattr(obj, field):
            continue
        v = getattr(obj, field)
        if v is None or (name == "stack_threshold" and v == p.default):
            continue
        if isinstance(obj, Dielectric) and name == "eta" and isinstance(v, eqx.Module):
            model = ", ".join(f"{f.name}={float(getattr(v, f.name))!r}" for f in dataclasses.fields(v))
            comments.append(f"materials.m?: Dielectric(eta={type(v).__name__}({model})), "
                            f"written as its index at {REFERENCE_WAVELENGTH_NM} nm")
            v = float(obj.ior())
        if isinstance(v, (tuple, list)) and v and all(isinstance(c, config.sdf.SDF) for c in v):
            out[name] = [_node(c, config.SHAPES, comments) for c in v]
        elif isinstance(v, config.sdf.SDF):
            out[name] = _node(v, config.SHAPES, comments)
        elif type(v) in config.PARTS.values():
            out[name] = _node(v, config.PARTS, comments)
        elif type(v) in config.HEIGHTS.values():
            out[name] = _node(v, config.HEIGHTS, comments)
        else:
            out[name] = _value(v)
    return out


def _fmt(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"`jaxrt.config_writer`: {v} cannot be written (finite numbers only)")
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_fmt(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"`jaxrt.config_writer`: cannot write {type(v).__name__}")


def _is_tables(v):
    return isinstance(v, list) and v and all(isinstance(x, dict) for x in v)


def _table(lines, path, table, array=False):
    lines.append(f"[[{path}]]" if array else f"[{path}]")
    for k, v in table.items():
        if not isinstance(v, dict) and not _is_tables(v):
            lines.append(f"{k} = {_fmt(v)}")
    for k, v in table.items():
        if isinstance(v, dict):
            _table(lines, f"{path}.{k}", v)
        elif _is_tables(v):
            for x in v:
                _table(lines, f"{path}.{k}", x, array=True)


def dumps(scene, camera=None, settings=None):
    """TOML text of `scene` (and `camera`, a single camera, and the fields of `settings`
    that differ from the defaults) that `jaxrt.config.loads` reads back."""
    comments, lines = [], []
    materials = {f"m{i}": _node(m, config.MATERIALS, comments) for i, m in enumerate(scene.materials)}
    surface = _node(scene.surface, config.SHAPES, comments)
    lights = [_node(light, config.LIGHTS, comments) for light in scene.lights]
    fields = [_node(f, {"heightfield": type(f)}, comments) for f in scene.heightfields]
    for f in fields:
        f.pop("type")
    lines.append(f"background = {_fmt(_value(scene.background))}")
    if camera is not None:
        _table(lines, "camera", _node(camera, config.CAMERAS, comments))
    if settings is not None:
        default = RenderSettings()
        changed = {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)
                   if getattr(settings, f.name) != getattr(default, f.name)}
        changed = {k: list(v) if isinstance(v, tuple) else v for k, v in changed.items() if v is not None}
        if "kernel" in changed:  # KernelOptions: its changed fields, as a [settings.kernel] table
            k, k0 = changed["kernel"], default.kernel
            changed["kernel"] = {f.name: getattr(k, f.name) for f in dataclasses.fields(k)
                                 if getattr(k, f.name) != getattr(k0, f.name)}
        _table(lines, "settings", changed)
    for name, m in materials.items():
        _table(lines, f"materials.{name}", m)
    for light in lights:
        _table(lines, "lights", light, array=True)
    for f in fields:
        _table(lines, "heightfields", f, array=True)
    _table(lines, "surface", surface)
    header = ["# Written by jaxrt.config_writer."] + [f"# {c}" for c in comments]
    return "\n".join(header + lines) + "\n"


def dump(path, scene, camera=None, settings=None):
    """Write `dumps(scene, camera, settings)` to `path`."""
    text = dumps(scene, camera, settings)
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)
