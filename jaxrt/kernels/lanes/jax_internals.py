"""Every name the lane interpreter takes from JAX's internals, in one place: jaxpr types
(`jax.extend.core`), the tracer type, dead-code elimination of jaxprs
(`jax._src.interpreters.partial_eval`), the names of primitives and the parameters
whose layout changes between JAX versions (a scan's `num_consts`/`num_carry` in jax
≤ 0.10, its `ft_in` trees in 0.11; a while loop's `cond_nconsts`...). Checked on jax
0.10.2 and 0.11.2. (The rules read the documented parameters of `jax.lax`'s primitives
— `dimension_numbers`, `axes`, `new_sizes`... — where they use them; `_RULES` in
`interpreter.py` maps primitive names to rules.)"""

import functools

import jax
from jax import lax
from jax.extend import core as jcore

ClosedJaxpr = jcore.ClosedJaxpr
Jaxpr = jcore.Jaxpr
Tracer = jax.core.Tracer
jax_array = jax.Array


def is_literal(v):
    """A jaxpr variable that is a literal (an inline constant)."""
    return isinstance(v, jcore.Literal)


def is_dropvar(v):
    """An output variable that nothing reads (`_`)."""
    return isinstance(v, jcore.DropVar)


def dce_jaxpr(jaxpr, used_outputs, instantiate=False):
    """`partial_eval.dce_jaxpr`: (the jaxpr without what `used_outputs` do not need,
    which of its inputs are used)."""
    from jax._src.interpreters import partial_eval as pe

    return pe.dce_jaxpr(jaxpr, used_outputs, instantiate=instantiate)


#: Primitives applied element by element (`elementwise._elementwise`).
ELEMENTWISE = {
    "abs", "acos", "acosh", "add", "add_any", "and", "asin", "asinh", "atan", "atan2",
    "atanh", "cbrt", "ceil", "clamp", "convert_element_type", "copy", "copy_p", "cos",
    "cosh", "div", "eq", "erf", "erf_inv", "erfc", "exp", "exp2", "expm1", "floor", "ge",
    "gt", "integer_pow", "is_finite", "le", "lgamma", "log", "log1p", "logistic", "lt",
    "max", "min", "mul", "ne", "neg", "nextafter", "not", "or", "pow", "reduce_precision",
    "rem", "rsqrt", "select_n", "shift_left", "shift_right_arithmetic",
    "shift_right_logical", "sign", "sin", "sinh", "sqrt", "square", "stop_gradient",
    "sub", "tan", "tanh", "xor", "optimization_barrier_elem",
    "reshard", "sharding_constraint", "mesh_cast",
}
#: Elementwise primitives that return their operand (the last three change only where the
#: value lives: JAX inserts `reshard` in programs traced under `shard_map`, as for a
#: render on several devices, `RenderSettings.devices`).
IDENTITY = {"stop_gradient", "copy", "copy_p", "reshard", "sharding_constraint", "mesh_cast"}

#: Primitives of an uninitialised value (a cond's partial evaluation fills the residuals
#: of a branch that has none with them): lanes make it zeros (`structural._empty`).
EMPTY = ("empty2", "empty")

#: Primitives whose inner jaxpr is inlined (`control._call`).
CALLS = ("pjit", "jit", "closed_call", "core_call", "remat", "checkpoint", "custom_jvp_call",
         "custom_vjp_call", "custom_vjp_call_jaxpr")


@functools.cache
def default_params(name):
    """The parameters of an equation of `PRIMS[name]` as `jax.lax` makes it on this JAX
    (`mul` carries `out_dtype`, which jaxpr printing reads), for the equations that
    rules build (`elementwise._apply`)."""
    if name != "mul":
        return {}
    return dict(jax.make_jaxpr(lax.mul)(1.0, 1.0).eqns[0].params)


#: The `jax.lax` primitives that rules build from (`elementwise._apply`), by name.
PRIMS = {
    "add": lax.add_p, "mul": lax.mul_p, "max": lax.max_p, "min": lax.min_p,
    "and": lax.and_p, "or": lax.or_p, "select_n": lax.select_n_p, "eq": lax.eq_p,
    "gt": lax.gt_p, "lt": lax.lt_p, "ne": lax.ne_p, "xor": lax.xor_p,
    "convert_element_type": lax.convert_element_type_p, "clamp": lax.clamp_p,
    "sub": lax.sub_p, "div": lax.div_p, "not": lax.not_p, "abs": lax.abs_p,
    "floor": lax.floor_p, "sign": lax.sign_p, "ge": lax.ge_p,
}


def _closed(eqn):
    """The inner jaxpr of a call-like equation (pjit, custom_jvp_call, remat...) as a
    ClosedJaxpr, or None."""
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        j = eqn.params.get(key)
        if isinstance(j, jcore.ClosedJaxpr):
            return j
        if isinstance(j, jcore.Jaxpr):
            return jcore.ClosedJaxpr(j, ())
    return None


def _scan_counts(params):
    """(consts, carries) of a scan equation: jax ≤ 0.10 has num_consts/num_carry, jax
    0.11 the flat trees ft_in = (consts, carries, xs)."""
    if "num_consts" in params:
        return params["num_consts"], params["num_carry"]
    consts, carry, _ = (len(list(t.vals)) for t in params["ft_in"].unpack())
    return consts, carry


def while_parts(params):
    """(cond consts, body consts, cond jaxpr, body jaxpr) of a while equation; its
    operands are the cond consts, the body consts, then the carries."""
    return (params["cond_nconsts"], params["body_nconsts"], params["cond_jaxpr"],
            params["body_jaxpr"])


def has_while(jaxpr):
    """Whether `jaxpr` (a Jaxpr or ClosedJaxpr) holds a `while`, in its inner jaxprs too."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "while":
            return True
        for value in eqn.params.values():
            for sub in value if isinstance(value, (list, tuple)) else [value]:
                if isinstance(sub, (jcore.Jaxpr, jcore.ClosedJaxpr)) and has_while(sub):
                    return True
    return False
