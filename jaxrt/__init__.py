"""jaxrt: a differentiable ray marcher in JAX.

This module re-exports the public API; reading it is reading the API index.
"""

from . import xla as xla

xla.add_process_flags()  # before JAX starts its backend: it reads $XLA_FLAGS then

from . import bsdf as bsdf, config as config, heightfield as heightfield, io as io, sdf as sdf, spectral as spectral
from . import config_writer as config_writer, views as views
from .heightfield import HeightField as HeightField
from .camera import OrthographicCamera as OrthographicCamera, PerspectiveCamera as PerspectiveCamera
from .lights import DirectionalLight as DirectionalLight, PointLight as PointLight
from .render import Image as Image, render as render
from .scene import Scene as Scene
from .settings import KernelOptions as KernelOptions, RenderSettings as RenderSettings
from .views import orbit as orbit, render_views as render_views, stack_cameras as stack_cameras
from .trace import (
    Hit as Hit,
    intersect_plane as intersect_plane,
    intersect_sphere as intersect_sphere,
    sphere_trace as sphere_trace,
    surface_normal as surface_normal,
)

__version__ = "0.1.0"


def __getattr__(name):
    """`jaxrt.fit` (fitting drivers) is imported when first used: it imports optax and
    optimistix, 0.15 s of every `jaxrt render`."""
    if name == "fit":
        import importlib

        return importlib.import_module(f"{__name__}.fit")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
