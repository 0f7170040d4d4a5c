"""The shape language: signed distance primitives, combinations, placement, deformation."""

from .base import SDF as SDF, Primitive as Primitive
from .combine import (
    Intersection as Intersection,
    SmoothIntersection as SmoothIntersection,
    SmoothSubtraction as SmoothSubtraction,
    SmoothUnion as SmoothUnion,
    Subtraction as Subtraction,
    Union as Union,
    op_intersection as op_intersection,
    op_smooth_intersection as op_smooth_intersection,
    op_smooth_subtraction as op_smooth_subtraction,
    op_smooth_union as op_smooth_union,
    op_subtraction as op_subtraction,
    op_union as op_union,
)
from .deform import (
    Bend as Bend,
    Displace as Displace,
    SineDisplacement as SineDisplacement,
    Twist as Twist,
)
from .domain import (
    Repeat as Repeat,
    Rotate as Rotate,
    Scale as Scale,
    Transform as Transform,
    Translate as Translate,
    rotate_axis_angle as rotate_axis_angle,
)
from .grid import (
    Grid as Grid,
    eikonal_loss as eikonal_loss,
    redistance as redistance,
    resample as resample,
    upsample as upsample,
)
from .primitives import (
    Box as Box,
    Capsule as Capsule,
    Cone as Cone,
    Cylinder as Cylinder,
    Ellipsoid as Ellipsoid,
    Plane as Plane,
    RoundBox as RoundBox,
    Sphere as Sphere,
    Torus as Torus,
    sd_box as sd_box,
    sd_capsule as sd_capsule,
    sd_cone as sd_cone,
    sd_cylinder as sd_cylinder,
    sd_ellipsoid as sd_ellipsoid,
    sd_plane as sd_plane,
    sd_round_box as sd_round_box,
    sd_sphere as sd_sphere,
    sd_torus as sd_torus,
)
from .stack import stacked as stacked, unstacked as unstacked
