"""Shared code of the inverse-rendering studies (experiments/inverse/*.py).

A study is a `Study`: the true parameter values (a dict of arrays), `build(params) ->
(scene, cameras)` (cameras stacked on a view axis, `jaxrt.views`), the transforms that
keep values legal, the scale each parameter's error is measured against, and the
study's headline metrics with their targets. `run` does the rest, the same way for
every study:

1. targets: `jaxrt.render_views` of the true scene with the target settings (point
   sampling at 16 spp, silhouette off: the box-filtered truth);
2. start: every parameter perturbed by up to `perturbation` (10 %) of its error scale,
   with a fixed seed;
3. fit: Adam (`jaxrt.fit.adam`, cosine schedule, per-group rates) on the L2 image loss
   with the fit settings (silhouette on where outlines matter), through
   `jaxrt.fit.fit` with a checkpoint in the output folder (a rerun resumes). With
   `fit.debias = true` the loss sees the image of the target's estimator (box-filtered
   point samples) with the gradient of the fit's (silhouette-aware):
   I = I_fit + stop_gradient(I_target(θ) − I_fit), so that the true values are a
   stationary point whatever the silhouette term's dilation (a straight-through
   estimator; one more forward render per step, by the targets' own compiled program
   outside the gradient step: `jaxrt.fit.fit(refresh=...)`); then, with a `[refine]`
   table of `steps` > 0, BFGS or Levenberg–Marquardt from Adam's result (`refine`);
4. outputs under the output folder: results.json and results.md (every parameter:
   truth, start, fit, error; the metrics and whether they meet their targets; timing
   and machine), curves.png (loss and parameter errors against steps), grid.png (rows
   of views: target | start | fit | |fit − target|), fitted.toml (the fitted scene with
   view 0 and the target settings, `jaxrt.config_writer`), fitted.exr/.png (its render),
   config.json (the resolved config).

Error of a parameter element: |fit − truth| / max(|truth|, floor), floor the
parameter's entry in `Study.floors` (0: purely relative; positions use a length so that
coordinates near 0 are not measured against 0).
"""

import argparse
import json
import os
import platform
import time
import tomllib
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import jaxrt as jr
from jaxrt.config import ConfigError

ROOT = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- config


def parse_args(name, argv=None, doc=None):
    p = argparse.ArgumentParser(prog=f"experiments/inverse/{name}.py", description=doc)
    p.add_argument("--config", default=str(ROOT / "configs" / "experiments" / f"inverse_{name}.toml"))
    p.add_argument("--out", default=None, help=f"output folder (default results/inverse/{name}/)")
    p.add_argument("--quick", action="store_true", help="the small version (< 3 min on 2 CPU cores)")
    p.add_argument("--size", type=int, default=None, help="image width = height (overrides the config)")
    p.add_argument("--views", type=int, default=None, help="number of views (overrides the config)")
    p.add_argument("--steps", type=int, default=None, help="Adam steps (overrides the config)")
    p.add_argument("--fresh", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--refine-steps", type=int, default=None,
                   help="steps of the [refine] phase after Adam (0: none; overrides the config)")
    args = p.parse_args(argv)
    cfg = load_config(args.config, args.quick)
    if args.refine_steps is not None:
        cfg.setdefault("refine", {})["steps"] = args.refine_steps
    for key, value in (("size", args.size), ("views", args.views), ("steps", args.steps)):
        if value is not None:
            cfg["run"][key] = value
    out = Path(args.out) if args.out else ROOT / "results" / "inverse" / name
    return cfg, out, args


def _merge(base, over):
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v
    return base


def load_config(path, quick=False):
    """The study's TOML config; with `quick`, its [quick] table merged over the rest."""
    path = Path(path)
    try:
        cfg = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config ({e})") from None
    overrides = cfg.pop("quick", {})
    if quick:
        _merge(cfg, overrides)
    cfg["quick"] = bool(quick)
    for table in ("run", "fit", "target_settings", "fit_settings", "targets"):
        if not isinstance(cfg.get(table), dict):
            raise ConfigError(f"{path}: {table} = {cfg.get(table, '<missing>')!r}, expected a table")
    run = cfg["run"]
    for key in ("size", "views", "steps"):
        if not (isinstance(run.get(key), int) and run[key] >= 1):
            raise ConfigError(f"{path}: run.{key} = {run.get(key, '<missing>')!r}, expected an integer ≥ 1")
    for key in ("learning_rate", "perturbation"):
        if not isinstance(cfg["fit"].get(key), (int, float)) or cfg["fit"][key] < 0:
            raise ConfigError(f"{path}: fit.{key} = {cfg['fit'].get(key, '<missing>')!r}, expected a number ≥ 0")
    for table in ("target_settings", "fit_settings"):
        try:
            jr.RenderSettings(**cfg[table])
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{path}: {table}: {e}") from None
    return cfg


# --------------------------------------------------------------------------- study


class Study(NamedTuple):
    """One inverse problem.

    name       the study's name (output folder, tables).
    truth      name → array: the true values of the free parameters.
    build      params → (scene, cameras stacked on a view axis).
    transforms name → `jaxrt.fit.Transform` (a prefix of truth; None: identity).
    floors     name → error floor (see the module docstring; missing: 0).
    rates      name → per-group learning-rate scale for Adam (missing: 1).
    metrics    (fitted params, truth) → dict of headline metrics (lower is better),
               compared with the config's [targets] of the same names.
    """

    name: str
    truth: dict
    build: Callable
    transforms: dict
    floors: dict = {}
    rates: dict = {}
    metrics: Callable | None = None


def element_names(params):
    """['radius', 'offset[0]', ...] for every scalar of a dict of arrays, in leaf order."""
    out = []
    for k in params:
        a = np.asarray(params[k])
        out += [k] if a.ndim == 0 else [f"{k}[{','.join(map(str, i))}]" for i in np.ndindex(a.shape)]
    return out


def element_errors(params, truth, floors):
    """Errors of every scalar (module docstring), in `element_names` order."""
    out = []
    for k in truth:
        f, t = np.asarray(params[k], float).ravel(), np.asarray(truth[k], float).ravel()
        out.append(np.abs(f - t) / np.maximum(np.abs(t), floors.get(k, 0.0) or 1e-12))
    return np.concatenate(out)


def perturb(truth, floors, fraction, seed):
    """Every scalar moved by u · fraction · max(|x|, floor), u uniform in [−1, 1]."""
    rng = np.random.default_rng(seed)
    out = {}
    for k, v in truth.items():
        a = np.asarray(v, float)
        u = rng.uniform(-1.0, 1.0, a.shape)
        out[k] = jnp.asarray(a + u * fraction * np.maximum(np.abs(a), floors.get(k, 0.0)))
    return out


def _devices(cfg):
    """The devices the views are sharded over: `[run] devices` (0, the default: every
    local device; `jaxrt.render_views`)."""
    return cfg["run"].get("devices", 0)


def settings(cfg, which):
    return jr.RenderSettings(**cfg[which])


def machine():
    dev = jax.devices()[0]
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "jax": jax.__version__, "backend": jax.default_backend(),
            "device": getattr(dev, "device_kind", str(dev))}


# --------------------------------------------------------------------------- run


def run(study, cfg, out, fresh=False):
    """Fit `study` as configured by `cfg`, write the outputs under `out`; returns the
    results dict (also results.json)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg, indent=2, default=str))
    f, r = cfg["fit"], cfg["run"]
    target_settings, fit_settings = settings(cfg, "target_settings"), settings(cfg, "fit_settings")
    t0 = time.perf_counter()
    scene, cameras = study.build(study.truth)
    targets = jr.render_views(scene, cameras, target_settings, devices=_devices(cfg)).rgb
    targets.block_until_ready()
    t_target = time.perf_counter() - t0
    start = perturb(study.truth, study.floors, f["perturbation"], cfg.get("seed", 0))
    weights = None

    debias = bool(f.get("debias", False))

    def forward(p):  # the target's estimator at p: the targets' own compiled program
        return jr.render_views(*study.build(p), target_settings, devices=_devices(cfg)).rgb

    def loss(p, truth_like):
        scene, cameras = study.build(p)
        image = jr.render_views(scene, cameras, fit_settings, devices=_devices(cfg)).rgb
        if truth_like is not None:  # values of the target's estimator, gradients of the fit's
            image = image + jax.lax.stop_gradient(truth_like - image)
        return jr.fit.l2_loss(image, targets, weights)

    refresh = forward if debias else None

    steps = r["steps"]
    rates = {k: study.rates.get(k, 1.0) for k in study.truth}
    optimiser = jr.fit.adam(f["learning_rate"], steps, warmup=f.get("warmup", 0),
                            end_factor=f.get("end_factor", 0.01), scales=rates)
    errors, timing = [], {}
    record_every = max(1, steps // 100)

    def callback(info):
        if info.step == 1:
            timing["first_step"] = time.perf_counter() - t1
        if info.step % record_every == 0 or info.step == steps:
            errors.append((info.step, element_errors(info.params, study.truth, study.floors)))

    checkpoint = out / "checkpoint.npz"
    if fresh and checkpoint.exists():
        checkpoint.unlink()
    errors.append((0, element_errors(start, study.truth, study.floors)))
    t1 = time.perf_counter()
    result = jr.fit.fit(loss, start, optimiser, max_steps=steps, transforms=study.transforms,
                        callback=callback, checkpoint=str(checkpoint),
                        checkpoint_every=f.get("checkpoint_every", 50), progress=True,
                        refresh=refresh)
    t_fit = time.perf_counter() - t1
    final, refined = result.params, None
    if cfg.get("refine", {}).get("steps", 0) > 0:
        final, refined = refine(study, cfg, result.params, targets)
    fitted = {k: np.asarray(v) for k, v in final.items()}
    # the estimator's floor: the fit's loss at the true values (0 without bias)
    loss_truth = float(jr.fit.fit(loss, study.truth, optimiser, max_steps=0,
                                  transforms=study.transforms, refresh=refresh).loss)
    err = element_errors(fitted, study.truth, study.floors)
    last = result.steps + (refined["steps"] if refined else 0)
    if errors[-1][0] != last:  # a resumed run's or the refinement's last point
        errors.append((last, err))
    metrics = {"max_parameter_error": float(err.max()), "median_parameter_error": float(np.median(err))}
    if study.metrics is not None:
        metrics.update({k: float(v) for k, v in study.metrics(fitted, study.truth).items()})
    err0 = element_errors(start, study.truth, study.floors)
    start_metrics = {"max_parameter_error": float(err0.max()), "median_parameter_error": float(np.median(err0))}
    if study.metrics is not None:
        start_metrics.update({k: float(v) for k, v in study.metrics(start, study.truth).items()})
    met = {k: bool(metrics[k] <= v) for k, v in cfg["targets"].items() if k in metrics}

    # images: start and fit with the target settings (what a viewer compares)
    start_rgb = forward(start)
    fit_scene, fit_cameras = study.build(final)
    fit_images = jr.render_views(fit_scene, fit_cameras, target_settings, devices=_devices(cfg))
    one = jr.views.view(fit_cameras, 0)
    jr.io.write_exr(out / "fitted.exr", jax.tree.map(lambda x: x[0], fit_images))
    jr.io.write_png(out / "fitted.png", fit_images.rgb[0])
    jr.config_writer.dump(out / "fitted.toml", fit_scene, one, target_settings)
    image_grid(out / "grid.png", np.asarray(targets), np.asarray(start_rgb), np.asarray(fit_images.rgb),
               rows=cfg.get("grid_rows", 4))
    names = element_names(study.truth)
    curves(out / "curves.png", result.history, errors, names, study.name)
    rows = [{"name": n, "truth": float(t), "start": float(s), "fit": float(v), "error": float(e)}
            for n, t, s, v, e in zip(names, _flat(study.truth, study.truth), _flat(start, study.truth),
                                     _flat(fitted, study.truth), err)]
    results = {
        "study": study.name, "quick": cfg["quick"], "size": r["size"], "views": int(targets.shape[0]),
        "steps": int(result.steps), "stopped": result.result, "loss_start": float(result.history[0]),
        "debias": debias, "loss_fit": float(result.loss), "loss_truth": loss_truth, "refine": refined,
        "metrics": metrics, "metrics_start": start_metrics,
        "targets": cfg["targets"], "met": met,
        "seconds": {"targets": round(t_target, 2), "first_step": round(timing.get("first_step", float("nan")), 2),
                    "fit": round(t_fit, 2), "refine": refined and refined["seconds"],
                    "total": round(time.perf_counter() - t0, 2)},
        "machine": machine(), "parameters": rows,
        "error_history": {"steps": [s for s, _ in errors], "max": [float(e.max()) for _, e in errors]},
    }
    (out / "results.json").write_text(json.dumps(results, indent=2))
    md = markdown(results)
    (out / "results.md").write_text(md)
    print(md)
    return results


def refine(study, cfg, params, targets):
    """The `[refine]` phase after Adam: a second-order solver in one compiled program,
    on the images of the `[refine] settings` table's renders (default `target_settings`,
    the targets' own estimator: its value and its gradient belong to one function, and
    at the truth its loss is 0), over the parameters named in `free` (default all; the
    rest held at Adam's values), for at most `steps` steps. With `gradient_settings` (a
    settings table: "fit_settings") the image is the debiased one of `run` within the
    program, I_g + stop_gradient(I − I_g): the value of the `settings` render and the
    outline-aware derivatives of the other.

    `method`:
    - "bfgs" (default): `optimistix.BFGS` on the L2 loss (line-search evaluations count
      as steps). Its inverse-Hessian estimate follows the curvature where Adam's steps
      follow their schedule.
    - "levenberg-marquardt": `optimistix.LevenbergMarquardt` on the residuals
      I(θ) − target, through `jaxrt.fit.fit_least_squares`. Each step forms the
      Jacobian (one forward-mode pass per free float) and solves the damped normal
      equations (JᵀJ + λD) δ = −Jᵀr by QR: a valley that is flat in the loss (the
      conductor's η against κ, docs/inverse.md) but not singular in J is crossed in a
      few steps, where a gradient method follows it for thousands. Moré (1978), "The
      Levenberg–Marquardt algorithm: implementation and theory".

    The loss (residuals) is divided by its value at the start (its square root), so
    that the solver's tolerances (`rtol`, `atol`) are relative.

    Returns (params, info): info has the method, the steps, the losses before and after
    (and at the truth, the estimator's floor), why the solver stopped and the seconds
    taken."""
    r = cfg["refine"]
    method = r.get("method", "bfgs")
    if method not in ("bfgs", "levenberg-marquardt"):
        raise ConfigError(f"refine.method = {method!r}, expected \"bfgs\" or \"levenberg-marquardt\"")
    render_settings = settings(cfg, r.get("settings", "target_settings"))
    gradient_settings = settings(cfg, r["gradient_settings"]) if r.get("gradient_settings") else None
    free = list(r.get("free", study.truth))
    unknown = [k for k in free if k not in study.truth]
    if unknown:
        raise ConfigError(f"refine.free = {free}: {unknown} are not parameters of the study "
                          f"(expected names from {list(study.truth)})")
    held = {k: v for k, v in params.items() if k not in free}

    def image(p):
        scene, cameras = study.build({**held, **p})
        rgb = jr.render_views(scene, cameras, render_settings, devices=_devices(cfg)).rgb
        if gradient_settings is not None:  # its values, the derivatives of the other render's
            estimate = jr.render_views(scene, cameras, gradient_settings, devices=_devices(cfg)).rgb
            rgb = estimate + jax.lax.stop_gradient(rgb - estimate)
        return rgb

    def loss(p, scale):
        return jr.fit.l2_loss(image(p), targets) / scale

    def residuals(p, scale):  # Σ r² = loss / scale
        return jnp.ravel(image(p) - targets) / jnp.sqrt(scale * targets.size)

    t = time.perf_counter()
    start = {k: params[k] for k in free}
    scale = jnp.maximum(loss(start, 1.0), 1e-30)
    rtol, atol = r.get("rtol", 1e-8), r.get("atol", 1e-12)
    transforms = {k: study.transforms.get(k) for k in free}
    if method == "bfgs":
        out = jr.fit.fit(loss, start, optx.BFGS(rtol=rtol, atol=atol), args=scale,
                         max_steps=r["steps"], transforms=transforms)
    else:
        out = jr.fit.fit_least_squares(residuals, start, optx.LevenbergMarquardt(rtol=rtol, atol=atol),
                                       args=scale, max_steps=r["steps"], transforms=transforms)
    loss_end = float(loss(out.params, 1.0))
    at_truth = float(loss({k: study.truth[k] for k in free}, 1.0))
    info = {"method": method, "steps": out.steps, "free": free, "settings": r.get("settings", "target_settings"),
            "stopped": "converged" if out.result == optx.RESULTS.successful else "max_steps",
            "loss_start": float(scale), "loss_end": loss_end, "loss_truth": at_truth,
            "seconds": round(time.perf_counter() - t, 2)}
    print(f"refine: {info['steps']} {method} steps, loss {info['loss_start']:.3e} → {loss_end:.3e} "
          f"(at the truth {at_truth:.3e}), {info['seconds']} s", flush=True)
    return {**params, **out.params}, info


def _flat(params, order):
    return np.concatenate([np.asarray(params[k], float).ravel() for k in order])


# --------------------------------------------------------------------------- outputs


_METHOD_NAMES = {"bfgs": "BFGS", "levenberg-marquardt": "Levenberg–Marquardt"}


def markdown(res):
    lines = [f"# inverse/{res['study']}{' (quick)' if res['quick'] else ''}", "",
             f"{res['views']} views of {res['size']}×{res['size']}, {res['steps']} Adam steps "
             f"(stopped: {res['stopped']}; {'debiased loss' if res['debias'] else 'plain loss'}); loss {res['loss_start']:.3e} → {res['loss_fit']:.3e} "
             f"(at the true values: {res['loss_truth']:.3e}, the estimator's bias); "
             f"{res['seconds']['total']} s in all ({res['seconds']['first_step']} s first step with "
             f"compilation, {res['seconds']['fit']} s fit) on {res['machine']['device']} "
             f"({res['machine']['backend']}, {res['machine']['cpu_count']} CPUs).", "",
             "| metric | start | fit | target | met |", "|---|---|---|---|---|"]
    if res.get("refine"):
        r = res["refine"]
        lines[3:3] = ["", f"Then {r['steps']} {_METHOD_NAMES[r.get('method', 'bfgs')]} steps on the loss of `{r['settings']}` over "
                      f"{', '.join(r['free'])} (stopped: {r['stopped']}): loss {r['loss_start']:.3e} → "
                      f"{r['loss_end']:.3e} (at the true values: {r['loss_truth']:.3e}), {r['seconds']} s."]
    for k, v in res["metrics"].items():
        t = res["targets"].get(k)
        lines.append(f"| {k} | {res['metrics_start'].get(k, float('nan')):.4g} | {v:.4g} | "
                     f"{'' if t is None else t} | {'' if t is None else ('yes' if res['met'][k] else 'NO')} |")
    lines += ["", "| parameter | truth | start | fit | error |", "|---|---|---|---|---|"]
    for p in res["parameters"]:
        lines.append(f"| {p['name']} | {p['truth']:.6g} | {p['start']:.6g} | {p['fit']:.6g} | {p['error']:.2e} |")
    return "\n".join(lines) + "\n"


def _display(rgb):
    return np.clip(jr.io.srgb_encode(np.clip(rgb, 0.0, 1.0)), 0.0, 1.0)


def image_grid(path, targets, start, fitted, rows=4):
    """Rows of views: target | start | fit | |fit − target| (mean over channels, the
    colour scale's maximum printed on each row)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(rows, targets.shape[0])
    idx = np.linspace(0, targets.shape[0] - 1, n).round().astype(int)
    fig, axes = plt.subplots(n, 4, figsize=(6.4, 1.65 * n + 0.3), squeeze=False)
    for row, i in enumerate(idx):
        err = np.abs(fitted[i] - targets[i]).mean(-1)
        vmax = max(float(err.max()), 1e-6)
        for col, (img, title) in enumerate(((targets[i], "target"), (start[i], "start"),
                                            (fitted[i], "fit"), (None, "|fit − target|"))):
            ax = axes[row, col]
            if img is None:
                ax.imshow(err, cmap="magma", vmin=0.0, vmax=vmax, interpolation="nearest")
                ax.set_xlabel(f"max {vmax:.2g}", fontsize=6, labelpad=1)
            else:
                ax.imshow(_display(img), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(title, fontsize=8)
        axes[row, 0].set_ylabel(f"view {i}", fontsize=7)
    fig.tight_layout(pad=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def curves(path, history, errors, names, title):
    """Loss and parameter errors (max and each element, thin) against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(8.0, 3.0))
    a.semilogy(np.arange(len(history)), np.maximum(history, 1e-30), lw=1.2)
    a.set_xlabel("step")
    a.set_ylabel("L2 image loss")
    a.set_title(f"{title}: loss", fontsize=9)
    a.grid(alpha=0.3, which="both")
    steps = np.array([s for s, _ in errors])
    e = np.maximum(np.stack([x for _, x in errors]), 1e-9)
    for j in range(e.shape[1]):
        b.semilogy(steps, e[:, j], lw=0.5, alpha=0.35, color="C0")
    b.semilogy(steps, e.max(axis=1), lw=1.6, color="C3", label="max")
    b.semilogy(steps, np.median(e, axis=1), lw=1.2, color="C2", label="median")
    b.set_xlabel("step")
    b.set_ylabel("parameter error")
    b.set_title(f"{title}: {len(names)} parameters", fontsize=9)
    b.legend(fontsize=7)
    b.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
