"""Benchmark: where a value_and_grad on the fast backend spends its time, on the Warp scene.

The plain lane kernel (a render), the recording kernel (image + tape), the replay's
primal, its jvp, its vjp split into forward (residuals) and transpose, its
value_and_grad, and the whole value_and_grad of an L2 loss; medians of REPEATS turns in
one process (ratios to the plain kernel; XLA's flop counts see a loop body once).

    python experiments/bench/gradient_pieces.py [W H REPEATS] [--only-kernels] [--profile]

--profile: also the device time of every kernel of the recording kernel, the replay's
vjp forward, its transpose and the whole value_and_grad (`gpu_profile.print_kernel_times`).
"""
import sys
import time
from pathlib import Path
import equinox as eqx
import jax
import jax.numpy as jnp

import jaxrt as jr
from jaxrt import fit
from jaxrt.camera import pixel_samples
from jaxrt.render import _fused, _record, _replay, _sample_kernel, _cast, _dtype

ROOT = Path(__file__).resolve().parents[2]
args = [a for a in sys.argv[1:] if not a.startswith("--")]
w, h, reps = (int(a) for a in (args + ["128", "64", "5"][len(args):])[:3])
only_kernels = "--only-kernels" in sys.argv
profile = "--profile" in sys.argv
scene, camera, settings = jr.config.load(ROOT / "configs/scenes/warp_raymarch.toml", width=w, height=h)
settings = settings.replace(max_steps=128, shadow_steps=128, backend="auto", batch_size=4096)
scene, camera = _cast((scene, camera), _dtype(settings))
samples = pixel_samples(camera, settings.spp, settings.seed).astype(camera.eye.dtype)
kernel = _sample_kernel(settings)
grid = (h, w * settings.spp)
dyn, static = eqx.partition((scene, camera), eqx.is_array)
P = lambda d: eqx.combine(d, static)
kinds = []
def rec(d):
    out, k = _record(kernel, P(d), samples, settings, grid, (0, 0))
    kinds[:] = [k]
    return out
jax.eval_shape(rec, dyn)
kinds = kinds[0]
out = jax.jit(rec)(dyn)
tape = out["tape"]
target = 1.1 * out["image"]["rgb"]


def replay_loss(d, t):
    return fit.l2_loss(_replay(kernel, P(d), samples, t, kinds)["rgb"], target)


def full_loss(d):
    return fit.l2_loss(jr.render(*P(d), settings).rgb.reshape(-1, 3), target)
fns = {
    "plain kernel": jax.jit(lambda d: _fused(*P(d), samples, settings, kernel, grid, (0, 0))),
    "record kernel": jax.jit(rec),
    "replay primal": jax.jit(replay_loss),
    "replay jvp": jax.jit(lambda d, t: jax.jvp(lambda x: replay_loss(x, t), (d,), (d,))),
    "replay value_and_grad": jax.jit(jax.value_and_grad(replay_loss)),
    "value_and_grad": jax.jit(jax.value_and_grad(full_loss)),
}
if only_kernels:
    fns = {k: fns[k] for k in ("plain kernel", "record kernel")}
argsof = {"plain kernel": (dyn,), "record kernel": (dyn,), "value_and_grad": (dyn,)}
if not only_kernels:
    vjp_fwd = jax.jit(lambda d, t: jax.vjp(lambda x: replay_loss(x, t), d))
    val, pb = vjp_fwd(dyn, tape)
    fns["replay vjp forward (residuals)"] = vjp_fwd
    fns["replay transpose"] = jax.jit(lambda pb, g: pb(g))
    argsof["replay transpose"] = (pb, jnp.ones_like(val))
comp = {}
for k, f in fns.items():
    a = argsof.get(k, (dyn, tape))
    t0 = time.perf_counter(); c = f.lower(*a).compile(); comp[k] = time.perf_counter() - t0
    ca = c.cost_analysis()
    ca = ca[0] if isinstance(ca, (list, tuple)) else ca
    flops = ca.get("flops", float("nan")) if ca else float("nan")
    fns[k] = (c, a, flops)
    jax.block_until_ready(c(*a))
times = {k: [] for k in fns}
for _ in range(reps):
    for k, (c, a, _) in fns.items():
        t0 = time.perf_counter(); jax.block_until_ready(c(*a)); times[k].append(time.perf_counter() - t0)
med = lambda x: sorted(x)[len(x) // 2]
base = med(times["plain kernel"])
if only_kernels:
    r = med([a / b for a, b in zip(times["record kernel"], times["plain kernel"])])
    print(f"record / plain kernel, median of per-turn ratios: {r:.3f}")
print(f"warp {w}x{h}, jax {jax.__version__}, {jax.devices()[0].device_kind}, median of {reps}")
for k, (c, a, flops) in fns.items():
    print(f"{k:32s} {med(times[k])*1e3:9.2f} ms  {med(times[k])/base:5.2f}x plain  "
          f"XLA flops {flops:.3g}  compile {comp[k]:.0f} s")
if profile:
    sys.path.insert(0, str(Path(__file__).parent))
    from gpu_profile import print_kernel_times

    for k in ("record kernel", "replay vjp forward (residuals)", "replay transpose", "value_and_grad"):
        if k in fns:
            c, a, _ = fns[k]
            print_kernel_times(lambda c=c, a=a: c(*a), reps, k, top=15)
