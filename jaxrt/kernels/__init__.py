"""Fused kernels: the one-ray programs of jaxrt run lane-wise over blocks of rays.

- `eval_lanes`: interpret the jaxpr of a one-ray program on a block of rays (the package `lanes`).
- `map_samples`: the per-sample render pipeline on tiles (XLA) or in one Pallas GPU
  kernel (`fused.py`); selected by `RenderSettings.backend`.
"""

from .fused import map_samples as map_samples, resolve_backend as resolve_backend
from .lanes import Unsupported as Unsupported, eval_lanes as eval_lanes, lanes_of as lanes_of
