"""Benchmark: the size of ONE evaluation of an SDF node and of its gradient.

Every march site of a render inlines the scene SDF (and, for normals and Newton
steps, its gradient), so the equations of one evaluation multiply every site. For
each primitive, domain map, combination, deformation, and the showcase's surface,
this prints the equations (inner jaxprs included, as `experiments/bench/compile.py`
counts them) of

    make_jaxpr(vmap(f))(points)                  value
    make_jaxpr(vmap(value_and_grad(f)))(points)  value and ∇_p f
    make_jaxpr(vmap(grad(f, node)))(points)      ∇_θ f (parameters)

    python experiments/bench/sdf_eqns.py [--prims] [--json out.json]
"""

import argparse
import collections
import json
from pathlib import Path

import jax
import jax.numpy as jnp

ROOT = Path(__file__).resolve().parents[2]


def count(jaxpr, prims=None):
    """Equations of `jaxpr` with those of its inner jaxprs (jit, custom_jvp, scan…)."""
    n = 0
    for e in jaxpr.eqns:
        n += 1
        if prims is not None:
            prims[e.primitive.name] += 1
        for v in e.params.values():
            for s in (v if isinstance(v, (list, tuple)) else [v]):
                if hasattr(s, "jaxpr"):
                    n += count(s.jaxpr if hasattr(s.jaxpr, "eqns") else s.jaxpr.jaxpr, prims)
                elif hasattr(s, "eqns"):
                    n += count(s, prims)
    return n


def sizes(node, prims=None):
    """(value, value_and_grad, param grad) equation counts of `node` under vmap."""
    pts = jnp.zeros((4, 3))
    v = count(jax.make_jaxpr(jax.vmap(node))(pts).jaxpr, prims)
    vg = count(jax.make_jaxpr(jax.vmap(jax.value_and_grad(node)))(pts).jaxpr)
    pg = count(jax.make_jaxpr(jax.vmap(lambda p: jax.grad(lambda s: s(p))(node)))(pts).jaxpr)
    return v, vg, pg


def nodes():
    from jaxrt import sdf
    from jaxrt.config import load

    s = sdf.Sphere(0.5)
    out = {
        "Sphere": s,
        "Plane": sdf.Plane((0.0, 1.0, 0.0), 0.1),
        "Box": sdf.Box((0.3, 0.4, 0.5)),
        "RoundBox": sdf.RoundBox((0.3, 0.4, 0.5), 0.1),
        "Torus": sdf.Torus(0.5, 0.2),
        "Cone": sdf.Cone(0.5, 1.0),
        "Capsule": sdf.Capsule(0.5, 0.2),
        "Cylinder": sdf.Cylinder(0.5, 0.5),
        "Ellipsoid": sdf.Ellipsoid((0.3, 0.5, 0.4)),
        "Translate(Sphere)": sdf.Translate(s, (0.1, 0.2, 0.3)),
        "Rotate(Sphere)": sdf.Rotate(s, (0.0, 1.0, 0.0), 30.0),
        "Transform(Sphere)": sdf.Transform(s, translation=(0.1, 0.2, 0.3)),
        "Scale(Sphere)": sdf.Scale(s, 0.5),
        "Repeat(Sphere)": sdf.Repeat(s, (1.0, 0.0, 0.0), count=(3, 0, 0)),
        "Twist(Sphere)": sdf.Twist(s, 1.0, 1.0),
        "Bend(Sphere)": sdf.Bend(s, 0.5, 1.0),
        "Displace(Sphere)": sdf.Displace(s),
        "Union(Sphere,Sphere)": sdf.Union(s, sdf.Sphere(0.3)),
        "Intersection(Sphere,Box)": sdf.Intersection(s, sdf.Box((0.3, 0.4, 0.5))),
        "Subtraction(Sphere,Sphere)": sdf.Subtraction(s, sdf.Sphere(0.3)),
        "SmoothUnion(Sphere,Sphere)": sdf.SmoothUnion(s, sdf.Sphere(0.3), 0.2),
    }
    scene = load(ROOT / "jaxrt/data/showcase.toml", width=32, height=24)[0]
    out["showcase surface"] = scene.surface
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--prims", action="store_true", help="primitive histogram of the showcase value")
    ap.add_argument("--json", help="write the table here")
    args = ap.parse_args(argv)
    table = {}
    print(f"{'node':30s} {'value':>7s} {'v&grad':>7s} {'∇θ':>7s}")
    for name, node in nodes().items():
        prims = collections.Counter() if name == "showcase surface" else None
        table[name] = sizes(node, prims)
        print(f"{name:30s} {table[name][0]:7d} {table[name][1]:7d} {table[name][2]:7d}")
    if args.prims:
        print(" ".join(f"{k}:{n}" for k, n in prims.most_common(20)))
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
