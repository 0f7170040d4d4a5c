"""Scene: a surface (an SDF tree), height fields, materials, lights and a background colour."""

import equinox as eqx
import jax.numpy as jnp

from .bsdf.base import Material, rgb
from .heightfield import HeightField
from .lights import DirectionalLight, PointLight
from .sdf.base import SDF


class Scene(eqx.Module):
    """Everything that is rendered.

    surface     an `jaxrt.sdf` node; its primitives' `material` indices select from
                `materials`.
    materials   a sequence of `jaxrt.bsdf` materials.
    lights      a sequence of `PointLight` / `DirectionalLight`.
    background  RGB radiance of rays that miss (differentiable).
    heightfields  a sequence of `jaxrt.heightfield.HeightField` surfaces y = h(x, z),
                marched with the notes' height-field algorithm (growing steps, linear
                interpolation of the crossing) alongside the sphere-traced `surface`;
                the nearest hit wins. Their `material` indices select from
                `materials` too. (A HeightField can also go inside `surface`, where it
                is sphere-traced with its distance bound instead.)

    The structure (node and material types, counts, indices) is static; every float
    is a differentiable leaf.
    """

    surface: SDF
    materials: tuple
    lights: tuple
    background: jnp.ndarray
    heightfields: tuple

    def __init__(self, surface, materials, lights=(), background=(0.0, 0.0, 0.0),
                 heightfields=()):
        if not isinstance(surface, SDF):
            raise TypeError(f"`Scene(surface=...)` must be a jaxrt.sdf node, got {type(surface).__name__}")
        materials = tuple(materials)
        if not materials:
            raise ValueError("`Scene(materials=...)` needs at least one material")
        for i, m in enumerate(materials):
            if not isinstance(m, Material):
                raise TypeError(f"`Scene(materials[{i}])` must be a jaxrt.bsdf material, got {type(m).__name__}")
        lights = tuple(lights)
        for i, light in enumerate(lights):
            if not isinstance(light, (PointLight, DirectionalLight)):
                raise TypeError(f"`Scene(lights[{i}])` must be a PointLight or DirectionalLight, got {type(light).__name__}")
        heightfields = tuple(heightfields)
        for i, field in enumerate(heightfields):
            if not isinstance(field, HeightField):
                raise TypeError(f"`Scene(heightfields[{i}])` must be a jaxrt.heightfield.HeightField, got {type(field).__name__}")
        used = set(surface.material_ids())
        for field in heightfields:
            used |= field.material_ids()
        missing = sorted(i for i in used if not 0 <= i < len(materials))
        if missing:
            raise ValueError(
                f"`Scene`: the surface and height fields use material indices {missing}, but only "
                f"{len(materials)} materials are given (valid: 0..{len(materials) - 1})"
            )
        self.surface = surface
        self.materials = materials
        self.lights = lights
        self.background = rgb(background, "Scene(background=...)")
        self.heightfields = heightfields

    def flags(self, name):
        """True if any material has the static flag `name` (e.g. "has_transmission")."""
        return any(getattr(m, name) for m in self.materials)
