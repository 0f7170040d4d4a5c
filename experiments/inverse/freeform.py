"""Free-form shape from images: a voxel-grid SDF (`jaxrt.sdf.Grid`) fitted to views of a
shape that no single primitive describes, coarse to fine (Vicini et al. 2022,
"Differentiable signed distance function rendering", in its simplest form).

The truth is built from the project's CSG: a rounded box smoothly joined to a ring (a
torus standing in the xy plane) with a spherical dent cut into the box's front face.
Targets: `views` cameras on a Fibonacci band of elevations around it, point-sampled at
`target_spp` samples per pixel with `silhouette = false` (the box-filtered truth), lit
by coloured directional lights (the shading encodes the normal), no shadows.

The fit: the grid's samples start as the visual hull of the targets' silhouettes
(`start = "visual_hull"`: space carving, a vertex is outside if any view sees
background there; it cannot see the dent) or as a sphere enclosing the shape
(`start = "sphere"`), and are moved by Adam (`jaxrt.fit.adam`, cosine schedule, a step of `learning_rate` cells) on

    loss = mean over views, pixels, channels of (render(grid) − target)²
           + eikonal_weight · eikonal_loss(grid, band = eikonal_band cells),

the renders at `fit_spp` with `silhouette = true` (outlines have gradients there;
without it only shading would move the surface). That estimator dilates outlines by
about `silhouette_width` pixels, a bias that the fit would undo by shrinking the shape
(at 24×24, a pixel is 3% of the shape's size); with `unbiased_spp` > 0 the image in
the loss is I_sil + stop_gradient(I_point − I_sil): its value is a point-sampled
render at `unbiased_spp` spp with `silhouette = false` (the targets' estimator, so the
residual vanishes at the true shape), its gradient the silhouette-aware one. Every
`redistance_every` steps, and at the end of each stage (only there with
`redistance_every = 0`), `jaxrt.sdf.redistance` makes the samples a distance field
again; with `reset_moments = true` Adam's moments are then forgotten
(`jaxrt.fit.reset_moments`), else kept. Stages double the cells, (n − 1) → 2 (n − 1),
and start from `jaxrt.sdf.upsample` of the previous one, which is exact: the coarse grid
is a fine grid with the same interpolant. So the renderer and its gradient are compiled once, for the
finest grid: a coarse stage renders its grid upsampled to the finest resolution (the
same shape) and pulls the gradient back through the (linear) upsampling.

Metrics, against the true surface, every `metrics_every` steps:
- volume IoU: inside/outside of both shapes on an `iou_resolution`³ lattice over the
  grid's box;
- Chamfer distance ½ (mean_a min_b |a − b| + mean_b min_a |a − b|) between surface
  samples of both shapes (points of a `chamfer_resolution`³ lattice within one spacing
  of the surface, jittered, projected onto it by Newton steps p ← p − f ∇f / |∇f|²),
  reported as a fraction of the true shape's bounding-box diagonal.

Writes under `--out` (default results/inverse/freeform/, or .../quick with --quick):
results.json (config, timings, curves, final metrics, targets met), results.md (a
table), curves.png (loss and metrics over the steps), images.png (rows of views:
target | start | fit | |error|), fitted_grid.npy + fitted.toml (the fitted scene,
which `jaxrt.config.load` reads), render.exr (the fitted scene's render from that
file) and config.json (the resolved config).

    python experiments/inverse/freeform.py [--quick] [--config ...] [--out DIR]
        [--views V] [--width W] [--height H] [--stages 33,65,129] [--iterations 250,250,150]
        [--set KEY=VALUE ...]   (any key of the config, VALUE a TOML value)
"""

import argparse
import dataclasses
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxrt as jr
from jaxrt import sdf

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "experiments" / "inverse_freeform.toml"


def load_config(path, quick=False):
    """The experiment's TOML config; with `quick`, its [quick] table overrides."""
    cfg = tomllib.loads(Path(path).read_text())
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)
    return cfg


# -- the problem --------------------------------------------------------------------------


def true_shape(cfg):
    """SmoothUnion(rounded box, ring) minus a sphere (the dent)."""
    box = sdf.RoundBox(cfg["box_half_extents"], cfg["box_radius"])
    ring = sdf.Rotate(sdf.Torus(cfg["torus_major_radius"], cfg["torus_minor_radius"]),
                      axis=(1.0, 0.0, 0.0), angle=90.0)
    dent = sdf.Translate(sdf.Sphere(cfg["dent_radius"]), cfg["dent_centre"])
    return sdf.Subtraction(sdf.SmoothUnion(box, ring, cfg["blend"]), dent)


def cameras(cfg):
    """`views` cameras looking at the origin from a Fibonacci band: sin(elevation)
    evenly spaced in [sin(min), sin(max)], azimuths by the golden angle."""
    n = cfg["views"]
    lo, hi = (math.sin(math.radians(cfg[k])) for k in ("min_elevation", "max_elevation"))
    golden = math.pi * (3.0 - math.sqrt(5.0))
    out = []
    for k in range(n):
        s = lo + (hi - lo) * (k + 0.5) / n
        c, phi = math.sqrt(1.0 - s * s), golden * k
        eye = cfg["distance"] * np.array([c * math.sin(phi), s, -c * math.cos(phi)])
        out.append(jr.PerspectiveCamera(eye=eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                                        fov=cfg["fov"], width=cfg["width"], height=cfg["height"]))
    return jr.stack_cameras(out)


def make_scene(cfg, surface):
    lights = [jr.DirectionalLight(direction=d, irradiance=e)
              for d, e in zip(cfg["light_directions"], cfg["light_irradiance"])]
    return jr.Scene(surface=surface, materials=[jr.bsdf.Lambert(albedo=cfg["albedo"])],
                    lights=lights, background=cfg["background"])


def settings(cfg, target):
    common = dict(shadows="none", max_steps=cfg["max_steps"], aovs=())
    if target:
        return jr.RenderSettings(spp=cfg["target_spp"], silhouette=False, **common)
    return jr.RenderSettings(spp=cfg["fit_spp"], silhouette=True,
                             silhouette_width=cfg["silhouette_width"],
                             silhouette_gradient=cfg.get("silhouette_gradient", "ramp"), **common)


def grid(cfg, values):
    return sdf.Grid(values, cfg["grid_lower"], cfg["grid_upper"])


def visual_hull(cfg, cams, targets, n):
    """Start values on an n³ grid: the visual hull of the targets' silhouettes (space
    carving). A pixel is background where every channel is within `hull_threshold` of
    the background colour (so a partly covered outline pixel is object). A vertex is outside if it projects onto background in any
    view; the ±h/2 labels are then redistanced into a distance field."""
    x = np.asarray(vertices_np(cfg, n)).reshape(-1, 3)
    inside = np.ones(len(x), bool)
    bg = np.asarray(cfg["background"], np.float32)
    for i in range(cfg["views"]):
        cam = jr.views.view(cams, i)
        img = np.asarray(targets[i])
        mask = np.any(np.abs(img - bg) > cfg["hull_threshold"], axis=-1)
        u, v, w = (np.asarray(a, float) for a in cam.frame())
        rel = x - np.asarray(cam.eye, float)
        z = rel @ w
        tan_half = math.tan(math.radians(float(cam.fov)) / 2.0)
        sx = (rel @ u) / (z * cam.aspect * tan_half)
        sy = (rel @ v) / (z * tan_half)
        px = np.floor((sx + 1.0) * 0.5 * cam.width).astype(int)
        py = np.floor((1.0 - sy) * 0.5 * cam.height).astype(int)
        seen = (z > 0) & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)
        hit = np.zeros(len(x), bool)
        hit[seen] = mask[py[seen], px[seen]]
        inside &= hit | ~seen
    h = float(np.max((np.asarray(cfg["grid_upper"]) - np.asarray(cfg["grid_lower"])) / (n - 1)))
    labels = np.where(inside, -0.5 * h, 0.5 * h).reshape(n, n, n).astype(np.float32)
    return sdf.redistance(grid(cfg, labels)).values


def vertices_np(cfg, n):
    lo, hi = np.asarray(cfg["grid_lower"]), np.asarray(cfg["grid_upper"])
    axes = [np.linspace(lo[a], hi[a], n) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1)


# -- metrics ------------------------------------------------------------------------------


def lattice(cfg, n):
    """Points of an n³ lattice over the grid's box ([n³, 3]) and its spacing."""
    lo, hi = np.asarray(cfg["grid_lower"]), np.asarray(cfg["grid_upper"])
    axes = [np.linspace(lo[a], hi[a], n) for a in range(3)]
    p = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return p.astype(np.float32), float(np.max((hi - lo) / (n - 1)))


class Metrics:
    """Volume IoU and Chamfer distance against the true shape (module docstring)."""

    def __init__(self, cfg, truth):
        self.cfg = cfg
        self.iou_points, _ = lattice(cfg, cfg["iou_resolution"])
        self.chamfer_points, self.spacing = lattice(cfg, cfg["chamfer_resolution"])
        self.samples = 4 * cfg["chamfer_resolution"] ** 2  # ~ the surface's lattice points
        self.rng = np.random.default_rng(cfg["seed"])
        self._project = jax.jit(jax.vmap(_project, in_axes=(None, 0)))
        self._eval = jax.jit(jax.vmap(lambda f, p: f(p), in_axes=(None, 0)))
        self.truth = truth
        self.inside_true = np.asarray(self._eval(truth, self.iou_points)) < 0.0
        self.surface_true = self.surface(truth)
        from scipy.spatial import cKDTree
        self.tree_true = cKDTree(self.surface_true)
        lo, hi = self.surface_true.min(0), self.surface_true.max(0)
        self.diagonal = float(np.linalg.norm(hi - lo))

    def surface(self, f):
        """`samples` points on the zero level set of `f` (a jaxrt SDF node)."""
        d = np.asarray(self._eval(f, self.chamfer_points))
        near = self.chamfer_points[np.abs(d) < self.spacing]
        if len(near) == 0:
            return np.zeros((1, 3), np.float32)
        pick = near[self.rng.integers(0, len(near), self.samples)]
        pick = pick + self.rng.uniform(-0.5, 0.5, pick.shape).astype(np.float32) * self.spacing
        p, r = (np.asarray(x) for x in self._project(f, pick))
        ok = np.abs(r) < 1e-3 * self.spacing
        return p[ok] if ok.any() else p[:1]

    def __call__(self, g):
        from scipy.spatial import cKDTree
        inside = np.asarray(self._eval(g, self.iou_points)) < 0.0
        iou = float(np.sum(inside & self.inside_true) / max(np.sum(inside | self.inside_true), 1))
        s = self.surface(g)
        d_fit_to_true, _ = self.tree_true.query(s)
        d_true_to_fit, _ = cKDTree(s).query(self.surface_true)
        chamfer = 0.5 * (float(np.mean(d_fit_to_true)) + float(np.mean(d_true_to_fit)))
        return dict(iou=iou, chamfer=chamfer, chamfer_rel=chamfer / self.diagonal,
                    hausdorff_rel=float(max(d_fit_to_true.max(), d_true_to_fit.max())) / self.diagonal)


def _project(f, p, steps=8):
    """p moved onto f's zero level set by Newton steps p ← p − f ∇f / |∇f|²; (p, f(p))."""
    for _ in range(steps):
        d, g = jax.value_and_grad(f)(p)
        p = p - d * g / jnp.maximum(jnp.sum(g * g), 1e-12)
    return p, f(p)


# -- the fit ------------------------------------------------------------------------------


def fit(cfg, log=print):
    """Run the study; returns (results dict, images and grids for the figures)."""
    t_start = time.perf_counter()
    truth = true_shape(cfg)
    cams = cameras(cfg)
    lo, hi = cfg["grid_lower"], cfg["grid_upper"]
    stages, iterations = list(cfg["stages"]), list(cfg["iterations"])
    if len(stages) != len(iterations):
        raise ValueError(f"stages {stages} and iterations {iterations} must have one entry each")
    finest = stages[-1]
    for n in stages:
        if (finest - 1) % (n - 1):
            raise ValueError(f"stage of {n} vertices: (n − 1) must divide {finest - 1}, the finest stage's cells")

    t = time.perf_counter()
    targets = jr.render_views(make_scene(cfg, truth), cams, settings(cfg, True), devices=cfg.get('devices', 0)).rgb
    targets.block_until_ready()
    log(f"targets: {cfg['views']} views of {cfg['width']}x{cfg['height']} at {cfg['target_spp']} spp "
        f"in {time.perf_counter() - t:.1f} s (with compilation)")

    metrics = Metrics(cfg, truth)
    log(f"true surface: {len(metrics.surface_true)} samples, bounding-box diagonal {metrics.diagonal:.4f}")
    fit_settings = settings(cfg, False)

    point_settings = dataclasses.replace(settings(cfg, True), spp=max(cfg["unbiased_spp"], 1))

    @jax.jit
    def loss_grad(fine):
        point = None
        if cfg["unbiased_spp"] > 0:  # no gradient: a constant of image_loss
            point = jr.render_views(make_scene(cfg, grid(cfg, fine)), cams, point_settings,
                                       devices=cfg.get('devices', 0)).rgb

        def image_loss(v):
            image = jr.render_views(make_scene(cfg, grid(cfg, v)), cams, fit_settings,
                                   devices=cfg.get('devices', 0)).rgb
            if point is not None:  # value: point-sampled; gradient: silhouette-aware
                image = image + jax.lax.stop_gradient(point - image)
            return jr.fit.l2_loss(image, targets)

        return jax.value_and_grad(image_loss)(fine)

    if cfg["start"] == "visual_hull":
        values = visual_hull(cfg, cams, targets, stages[0])
    elif cfg["start"] == "sphere":
        values = sdf.Grid.from_sdf(sdf.Sphere(cfg["start_radius"]), lo, hi, stages[0]).values
    else:
        raise ValueError(f"start = {cfg['start']!r}, expected 'visual_hull' or 'sphere'")
    values = jnp.asarray(values, jnp.float32)
    start_values = values
    history = dict(step=[], loss=[], eikonal=[], metric_step=[], iou=[], chamfer_rel=[])
    stage_rows, step, compile_s = [], 0, None
    for s, (n, iters) in enumerate(zip(stages, iterations)):
        t_stage = time.perf_counter()
        factor = (finest - 1) // (n - 1)
        h = float(np.max((np.asarray(hi) - np.asarray(lo)) / (n - 1)))
        optimiser = jr.fit.adam(cfg["learning_rate"] * h, iters, kind="cosine",
                                end_factor=cfg["end_factor"])
        state = optimiser.init(values)

        def up(v, factor=factor):
            return sdf.upsample(grid(cfg, v), factor).values if factor > 1 else v

        up_jit = jax.jit(up)

        @jax.jit
        def update(v, state, g_fine, h=h, up=up, optimiser=optimiser):
            _, pull = jax.vjp(up, v)
            (g,) = pull(g_fine)
            e, g_e = jax.value_and_grad(
                lambda v: sdf.eikonal_loss(grid(cfg, v), band=cfg["eikonal_band"] * h))(v)
            updates, state = optimiser.update(g + cfg["eikonal_weight"] * g_e, state, v)
            return optax.apply_updates(v, updates), state, e

        for it in range(iters):
            t_it = time.perf_counter()
            loss, g_fine = loss_grad(up_jit(values))
            values, state, e = update(values, state, g_fine)
            loss = float(loss)
            if compile_s is None:
                compile_s = time.perf_counter() - t_it
                log(f"first step (compiles the renderer's gradient): {compile_s:.1f} s")
            every = cfg["redistance_every"]
            if (every and (it + 1) % every == 0) or it + 1 == iters:
                values = sdf.redistance(grid(cfg, values)).values
                if cfg.get("reset_moments", False):
                    state = jr.fit.reset_moments(state)
            history["step"].append(step)
            history["loss"].append(loss)
            history["eikonal"].append(float(e))
            step += 1
            if it % cfg["metrics_every"] == 0 or it + 1 == iters:
                m = metrics(grid(cfg, values))
                m["lipschitz"] = float(grid(cfg, values).lipschitz())
                history["metric_step"].append(step)
                history["iou"].append(m["iou"])
                history["chamfer_rel"].append(m["chamfer_rel"])
                log(f"stage {n}³ step {it + 1:4d}/{iters}: loss {loss:.3e}  eikonal {float(e):.3e}  "
                    f"IoU {m['iou']:.4f}  Chamfer {100 * m['chamfer_rel']:.3f}% of the diagonal  L {m['lipschitz']:.2f}  "
                    f"({time.perf_counter() - t_stage:.1f} s)")
        stage_s = time.perf_counter() - t_stage
        stage_rows.append(dict(vertices=n, cells=n - 1, iterations=iters, loss=loss, **m,
                               seconds=stage_s, seconds_per_step=stage_s / iters))
        if s + 1 < len(stages):
            values = sdf.upsample(grid(cfg, values), (stages[s + 1] - 1) // (n - 1)).values

    fitted = grid(cfg, values)
    final = metrics(fitted)
    total_s = time.perf_counter() - t_start
    results = dict(
        final=final, stages=stage_rows, history=history, diagonal=metrics.diagonal,
        seconds_total=total_s, seconds_first_step=compile_s,
        device=str(jax.devices()[0].device_kind), backend=jax.default_backend(),
        targets=dict(chamfer_rel=cfg["target_chamfer"], iou=cfg["target_iou"],
                     chamfer_met=final["chamfer_rel"] <= cfg["target_chamfer"],
                     iou_met=final["iou"] >= cfg["target_iou"]),
        start=metrics(grid(cfg, start_values)),
    )
    return results, dict(truth=truth, cameras=cams, targets=targets, start=start_values, fitted=fitted)


# -- outputs ------------------------------------------------------------------------------


def write_outputs(cfg, results, parts, out, log=print):
    """Every output file (module docstring). The fitted scene is written as TOML and read
    back with `jaxrt.config.load`; the "fit" images and render.exr are renders of that
    file's scene, through the study's cameras at the targets' settings (one compiled
    program for them and the start's images: the start is upsampled to the fitted
    grid's resolution, which keeps its shape)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg, indent=2))
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(markdown(cfg, results))
    curves(results, out / "curves.png", cfg)
    fitted = parts["fitted"]
    np.save(out / "fitted_grid.npy", np.asarray(fitted.values, np.float32))
    write_scene(cfg, parts, out)
    scene, camera, render_settings = jr.config.load(out / "fitted.toml")
    fit_images = jr.render_views(scene, parts["cameras"], render_settings, devices=cfg.get('devices', 0)).rgb
    start = grid(cfg, parts["start"])
    start = sdf.upsample(start, (fitted.values.shape[0] - 1) // (start.values.shape[0] - 1))
    start_images = jr.render_views(make_scene(cfg, start), parts["cameras"], render_settings, devices=cfg.get('devices', 0)).rgb
    image_grid(cfg, parts["targets"], start_images, fit_images, out / "images.png")
    jr.io.write_exr(out / "render.exr", np.asarray(fit_images[0]))
    log(f"wrote {out}/: results.json, results.md, curves.png, images.png, fitted_grid.npy, "
        "fitted.toml, render.exr (view 0), config.json")


def markdown(cfg, results):
    rows = ["| stage | steps | image loss | Chamfer (% of diagonal) | IoU | time (s) | s/step |",
            "|---|---|---|---|---|---|---|"]
    start = results["start"]
    rows.append(f"| start ({cfg['start'].replace('_', ' ')}) | 0 | – | {100 * start['chamfer_rel']:.3f} | {start['iou']:.4f} | – | – |")
    for r in results["stages"]:
        rows.append(f"| {r['cells']}³ cells ({r['vertices']}³ samples) | {r['iterations']} | {r['loss']:.3e} "
                    f"| {100 * r['chamfer_rel']:.3f} | {r['iou']:.4f} | {r['seconds']:.1f} | {r['seconds_per_step']:.2f} |")
    f, t = results["final"], results["targets"]
    met = lambda ok: "met" if ok else "NOT met"
    return "\n".join([
        f"Free-form shape: a Grid SDF fitted to {cfg['views']} views of {cfg['width']}×{cfg['height']} "
        f"(targets {cfg['target_spp']} spp, silhouette off; fit {cfg['fit_spp']} spp, silhouette on), "
        f"on {results['device']} ({results['backend']}), {results['seconds_total']:.0f} s in all "
        f"(first step, with compilation: {results['seconds_first_step']:.0f} s).",
        "",
        *rows,
        "",
        f"Final: Chamfer {100 * f['chamfer_rel']:.3f}% of the bounding-box diagonal ({results['diagonal']:.3f}; "
        f"target ≤ {100 * t['chamfer_rel']:.1f}%: {met(t['chamfer_met'])}), "
        f"IoU {f['iou']:.4f} (target ≥ {t['iou']}: {met(t['iou_met'])}), "
        f"Hausdorff {100 * f['hausdorff_rel']:.2f}% of the diagonal.",
        "",
    ])


def curves(results, path, cfg):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = results["history"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].semilogy(h["step"], h["loss"], label="image loss (MSE)")
    ax[0].semilogy(h["step"], np.maximum(h["eikonal"], 1e-12), label="eikonal loss", alpha=0.7)
    ax[1].semilogy(h["metric_step"], np.asarray(h["chamfer_rel"]) * 100, "o-", label="Chamfer, % of diagonal")
    ax[1].semilogy(h["metric_step"], (1.0 - np.asarray(h["iou"])) * 100, "s-", label="1 − IoU, %")
    ax[1].axhline(100 * cfg["target_chamfer"], color="C0", ls=":", lw=1)
    ax[1].axhline(100 * (1 - cfg["target_iou"]), color="C1", ls=":", lw=1)
    edge = 0
    for r in results["stages"][:-1]:
        edge += r["iterations"]
        for a in ax:
            a.axvline(edge, color="grey", lw=0.8, ls="--")
    for a, title in zip(ax, ("losses", "metrics (dotted: targets)")):
        a.set_xlabel("Adam step")
        a.set_title(title)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def image_grid(cfg, target, start, fitted, path):
    """Rows of views `figure_views`: target | start | fit | |error| (|fit − target|, ×4)."""
    pick = [i for i in cfg["figure_views"] if i < cfg["views"]]
    gap, h, w = 2, cfg["height"], cfg["width"]
    canvas = np.ones((len(pick) * (h + gap) - gap, 4 * (w + gap) - gap, 3), np.float32)
    for r, i in enumerate(pick):
        row = (target[i], start[i], fitted[i], 4.0 * jnp.abs(fitted[i] - target[i]))
        for c, img in enumerate(row):
            canvas[r * (h + gap):r * (h + gap) + h, c * (w + gap):c * (w + gap) + w] = np.asarray(img)
    jr.io.write_png(path, canvas)


def write_scene(cfg, parts, out):
    """fitted.toml: the fitted scene (its grid from fitted_grid.npy) seen from view 0, at
    the targets' settings."""
    from jaxrt import config_writer

    placeholder = sdf.Grid(np.zeros((2, 2, 2)), cfg["grid_lower"], cfg["grid_upper"])
    text = config_writer.dumps(make_scene(cfg, placeholder), jr.views.view(parts["cameras"], 0),
                               settings(cfg, True))
    inline = "values = " + config_writer._fmt(np.zeros((2, 2, 2)).tolist())
    if inline not in text:
        raise RuntimeError("fitted.toml: the placeholder grid's values were not found")
    text = text.replace(inline, 'values = "fitted_grid.npy"')
    (out / "fitted.toml").write_text(text)


# -- command line -------------------------------------------------------------------------


def _ints(text):
    return [int(x) for x in text.split(",") if x.strip()]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default=str(CONFIG))
    parser.add_argument("--quick", action="store_true", help="tiny images, a 16³ → 32³ fit")
    parser.add_argument("--out", default=None)
    parser.add_argument("--views", type=int)
    parser.add_argument("--width", type=int)
    parser.add_argument("--height", type=int)
    parser.add_argument("--stages", type=_ints, help="vertex counts per stage, e.g. 33,65,129")
    parser.add_argument("--iterations", type=_ints, help="Adam steps per stage, e.g. 250,250,150")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="set a config key (VALUE a TOML value), e.g. reset_moments=true")
    args = parser.parse_args(argv)
    cfg = load_config(args.config, args.quick)
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in cfg:
            parser.error(f"--set {item}: {key!r} is not a key of {args.config}")
        cfg[key] = tomllib.loads(f"v = {value}")["v"]
    for key in ("views", "width", "height", "stages", "iterations"):
        if getattr(args, key) is not None:
            cfg[key] = getattr(args, key)
    if args.stages is not None and args.iterations is None and len(cfg["iterations"]) != len(cfg["stages"]):
        cfg["iterations"] = (list(cfg["iterations"]) + [cfg["iterations"][-1]] * len(cfg["stages"]))[:len(cfg["stages"])]
    out = Path(args.out) if args.out else ROOT / "results" / "inverse" / "freeform" / ("quick" if args.quick else "")
    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind}; stages {cfg['stages']}, "
          f"iterations {cfg['iterations']}, {cfg['views']} views of {cfg['width']}x{cfg['height']}", flush=True)
    results, parts = fit(cfg, log=lambda s: print(s, flush=True))
    write_outputs(cfg, results, parts, out)
    f = results["final"]
    print(f"final: Chamfer {100 * f['chamfer_rel']:.3f}% of the diagonal, IoU {f['iou']:.4f}; "
          f"targets: Chamfer ≤ {100 * cfg['target_chamfer']:.1f}% "
          f"{'met' if results['targets']['chamfer_met'] else 'NOT met'}, IoU ≥ {cfg['target_iou']} "
          f"{'met' if results['targets']['iou_met'] else 'NOT met'}; {results['seconds_total']:.0f} s", flush=True)
    return results


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
