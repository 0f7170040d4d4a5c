"""Marching: the bounded loops of a render, which carry no gradient, and their tape.

This side of the seam finds roots and minima (sphere tracing, shadow rays, height-field
marches, the silhouette searches), each with its own small options object; the other
side (`jaxrt.trace`, `jaxrt.lights`, `jaxrt.integrator`, `jaxrt.silhouette`) turns what
they found into differentiable values: Newton steps at a recorded root (implicit
gradients), penumbrae at a recorded minimum (envelope theorem), coverage at a recorded
near miss. `tape` records the marches of a render in the fast kernels and replays them
in a loop-free program whose VJP is the gradient (`jaxrt.render`).
"""

from . import tape as tape
from .shadow import SoftShadow as SoftShadow
from .sphere import SphereTracing as SphereTracing
