"""The loop form of the marches: "phases" (one copy of f per march) or "plain" (straight).

A march evaluates the scene SDF f at several kinds of points: the sphere march f(o),
every step and the secant finish of a ray out of budget; the soft-shadow march f(o),
every step, the sample after the last and the golden-section refinement; the Newton
polish and the origin settling one value and gradient per step. Two forms compute the
same values (to rounding):

- "phases": each kind of point is a phase of one loop whose every iteration evaluates
  f once, at the point its phase chooses (the values carried in the loop state, a
  select on the phase); short loops (Newton polish, settling) are loops. The program
  holds one inlined copy of f per march: the "jax" render program of the showcase
  has ~17.5k equations instead of ~31k, which XLA compiles that much faster.
- "plain": f(o) before the loop, the march's steps alone in it, the finish after it;
  loops of at most `PLAIN_UNROLL` iterations (`search.repeat`: Newton polish, origin
  settling, height-field refinement) as straight code. More copies of f, but the hot
  loop runs no phase logic, and a warp of lanes in lock-step (the Pallas kernel of
  `jaxrt.kernels.fused`) runs no extra iterations for its slowest lane's finish. On
  an H200 (Warp scene, 2048×1024, max_steps 64, "pallas") the bisection of
  docs/performance.md measured 0.511 ms at aa601d3, whose marches had these forms,
  and 1.089 ms with the phases.

The form is chosen where a one-ray program is traced (`using`): the fused backends
trace under `settings.kernel.march_form` (`jaxrt.KernelOptions`: "auto" is "plain"
for programs of at most `kernel.plain_max_lane_ops` lane operations, "phases" for
larger ones, `kernels.fused._trace_one`); anything else (the vmapped "jax" path)
traces under the default, "phases". The marches read it at trace time (`current`), so a
choice must be part of the jit cache key of whatever is traced under it: the
kernel options are.
"""

import contextlib
import threading

FORMS = ("phases", "plain")

#: In the "plain" form, `search.repeat` loops of at most this many iterations are
#: straight code (newton_steps, spawn_steps and a height field's refine_steps are
#: small); longer ones (golden sections, the silhouette's regula falsi) stay loops.
PLAIN_UNROLL = 4

_STATE = threading.local()


def current():
    """The form the marches traced now take: "phases" unless `using` says otherwise."""
    return getattr(_STATE, "form", "phases")


@contextlib.contextmanager
def using(form):
    """Context: marches traced inside it take `form` ("phases" or "plain")."""
    if form not in FORMS:
        raise ValueError(f"march form {form!r}: expected one of {FORMS}")
    previous = current()
    _STATE.form = form
    try:
        yield form
    finally:
        _STATE.form = previous

