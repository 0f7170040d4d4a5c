"""Run a one-ray program on a block of rays, one lane per ray ("structure of arrays").

jaxrt's kernels are written for one ray (`trace_radiance(scene, o, d, cone, settings)`)
and `jax.vmap` batches them. vmap keeps the shapes of the one-ray program and adds a
batch axis: a point becomes a [B, 3] array, a dot product a reduction over its last
axis, a sphere-tracing loop a masked loop over the batch. On a CPU this leaves many
small ops with strided access; inside a GPU kernel (Pallas/Triton) shapes like [B, 3]
are not even allowed (block shapes must be powers of two).

`eval_lanes` instead *scalarises* the one-ray program. It traces it once to a jaxpr and
interprets that jaxpr with every value of shape S held as a numpy object array of shape
S whose elements are lanes: a [B] array (one number per ray), a 0-d array (the same
for every ray: scene parameters) or a numpy scalar (a compile-time constant). Every
elementwise primitive is applied lane-wise; structural primitives (slice, reshape,
broadcast, concatenate, transpose, gather/scatter with constant indices, small
reductions and dot products) only rearrange or fold the object arrays, so they cost
nothing at run time. What is left is a flat program of [B] elementwise operations, which
XLA fuses into a few loops on the CPU and Triton compiles into one GPU kernel.

Control flow: a `while` whose condition varies between rays becomes one loop over the
block that runs while any lane is active; inactive lanes keep their state (the
semantics of `vmap` of a while loop: each ray stops where it would alone, and the block
stops when its last ray does). `cond` with a per-ray index evaluates every branch and
selects lane-wise. A `scan` is unrolled, or with `roll_scans` (the "fused"
backend) kept as one loop over lanes (`control._scan_rolled`), whose stacked outputs
stay arrays whose rows are sliced only where read (`values.Row`; the scene's leaves
too, on "fused"); in a Pallas kernel a scan over the kernel's parameters (a stacked
union) is one loop that loads each iteration's values (`control._scan_loaded`).
Dynamic indexing (`x[i]` with a per-ray `i`, as in a material table) becomes a chain
of selects over the possible indices.

The result is the same function as the one-ray program (same primitives, same order of
floating-point operations), so images agree with the vmapped path to rounding. The
forward pass only: differentiate through the reference path (see `fused.py`).

The modules, one job each:
  values          how values are held (lanes, constants, the evaluation context)
  elementwise     elementwise primitives on lanes, and the helpers rules build from
  structural      rearranging and folding primitives (reshape, slice, reductions, dot)
  indexing        gather/scatter/dynamic slices, per-ray indices enumerated
  control         calls, while, scan, cond
  interpreter     the jaxpr interpreter, the table of rules, `eval_lanes`
  gpu             GPU-only rewrites: fast math, fused multiply-adds, erfc, `Uniforms`
  jax_internals   every name taken from JAX's internals (jaxpr types, primitive
                  names, version-dependent parameters)
"""

from .control import Tables as Tables
from .gpu import Uniforms as Uniforms
from .interpreter import eval_lanes as eval_lanes, program_size as program_size
from .values import Unsupported as Unsupported, lanes_of as lanes_of, stack_lanes as stack_lanes

__all__ = ["eval_lanes", "lanes_of", "program_size", "stack_lanes", "Tables", "Uniforms",
           "Unsupported"]
