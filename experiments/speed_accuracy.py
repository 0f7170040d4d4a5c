"""Speed against accuracy: every RenderSettings dial swept alone and in named
combinations (the presets), on several scenes, against a converged reference.

    python experiments/speed_accuracy.py [--config configs/experiments/speed_accuracy.toml]
                                         [--scenes warp,showcase] [--out out/speed_accuracy]

For each scene: the reference is the scene's own settings with the `[reference]` dials
(float64, tight epsilon, large budgets, many samples). Every other setting is the
scene's settings with one dial changed (`[dials]`, or the scene's own `dials` list and `dial_values`), or
a named combination (`[combos]`, including `preset:NAME` = RenderSettings.preset(NAME)
on the scene's settings). Measured: compile time, median render time of `repeats`
renders, the RMSE and maximum of |rgb − reference| over the image (linear radiance),
and the median relative depth error over pixels that both hit. Writes per scene a
Pareto plot (time against RMSE, front drawn, presets starred), and `results.md` /
`results.json` with every row, under the output folder.
"""

import argparse
import json
import os
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/speed_accuracy.toml"))
    ap.add_argument("--scenes", default=None, help="comma-separated subset")
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true", help="the config's [quick] overrides")
    ap.add_argument("--settings", default=None,
                    help="comma-separated setting labels to (re)measure; a scene's other rows "
                         "are kept from the last results.json")
    args = ap.parse_args(argv)
    cfg = tomllib.loads(Path(args.config).read_text())
    if args.quick:
        cfg = _merge(cfg, cfg.get("quick", {}))

    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxrt as jr

    out_dir = Path(args.out or ROOT / cfg.get("out", "out/speed_accuracy"))
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config.json").write_text(json.dumps(cfg, indent=1))
    info = dict(device=jax.devices()[0].device_kind, backend=jax.default_backend(),
                cpu_cores=os.cpu_count(), jax=jax.__version__)
    print(info, flush=True)
    wanted = args.scenes.split(",") if args.scenes else None
    results = dict(info=info, scenes={})
    if wanted and (out_dir / "results.json").exists():  # keep the other scenes' results
        results["scenes"] = json.loads((out_dir / "results.json").read_text())["scenes"]
    for sc in cfg["scenes"]:
        if wanted and sc["name"] not in wanted:
            continue
        only = args.settings.split(",") if args.settings else None
        kept = [r for r in results["scenes"].get(sc["name"], []) if only and r["setting"] not in only]
        results["scenes"][sc["name"]] = run_scene(sc, cfg, jr, out_dir, only, kept)
        md = [f"# Speed against accuracy ({info['device']}, {info['backend']}, "
              f"{info['cpu_cores']} cores, jax {info['jax']})", "",
              "Times: CPU medians after compilation on a 2-core machine shared with other "
              "jobs (noisy: compare within a scene, not across runs).", ""]
        for other in cfg["scenes"]:
            if other["name"] in results["scenes"]:
                md += _markdown(other, results["scenes"][other["name"]])
        (out_dir / "results.json").write_text(json.dumps(results, indent=1, default=str))
        (out_dir / "results.md").write_text("\n".join(md))
    print(f"wrote {out_dir / 'results.md'}")
    return results


def _merge(a, b):
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def run_scene(sc, cfg, jr, out_dir, only=None, kept=()):
    scene, camera, base = jr.config.load(ROOT / sc["path"], width=sc["width"], height=sc["height"])
    base = base.replace(**sc.get("settings", {}))
    ref_settings = base.replace(**cfg["reference"], **sc.get("reference", {}))
    repeats = cfg.get("repeats", 3)
    print(f"\n== {sc['name']} ({sc['width']}x{sc['height']}): reference {ref_settings}", flush=True)
    # the reference is cached next to the results (it takes minutes)
    cache = out_dir / f"reference_{sc['name']}.npz"
    key = repr((sc["path"], sc["width"], sc["height"], ref_settings))
    if cache.exists() and str(np.load(cache)["key"]) == key:
        z = np.load(cache)
        ref_rgb, ref_depth, ref_hit = z["rgb"], z["depth"], z["hit"]
        print("reference from", cache, flush=True)
    else:
        t0 = time.perf_counter()
        ref = jr.render(scene, camera, ref_settings)
        ref_rgb, ref_depth = np.asarray(ref.rgb, np.float64), np.asarray(ref.depth, np.float64)
        ref_hit = np.asarray(ref.coverage) > 0.5
        np.savez(cache, rgb=ref_rgb, depth=ref_depth, hit=ref_hit, key=key)
        print(f"reference rendered in {time.perf_counter() - t0:.1f} s", flush=True)

    settings = [("base", "scene settings", base)]
    dials = cfg["dials"]
    for dial in sc.get("dials", list(dials)):
        for value in sc.get("dial_values", {}).get(dial, dials[dial]):
            try:
                s = base.replace(**{dial: value})
            except ValueError as e:
                print(f"skip {dial}={value}: {e}")
                continue
            if s != base:
                settings.append((f"{dial}={value}", dial, s))
    for name, combo in cfg.get("combos", {}).items():
        if sc.get("combos") is not None and name not in sc["combos"]:
            continue
        combo = dict(combo)
        preset = combo.pop("preset", None)
        s = jr.RenderSettings.preset(preset, base=base) if preset else base
        settings.append((name, "combo", s.replace(**combo)))

    rows = list(kept)
    for label, dial, s in settings:
        if only and label not in only:
            continue
        row = measure(jr, scene, camera, s, repeats)
        err = errors(row.pop("image"), ref_rgb, ref_depth, ref_hit)
        row = dict(setting=label, dial=dial, **row, **err)
        rows.append(row)
        print(f"  {label:<28} {row['render_ms']:9.1f} ms  compile {row['compile_s']:5.1f} s  "
              f"rmse {row['rmse']:.2e}  max {row['max']:.2e}  depth {row['depth_rel']:.1e}",
              flush=True)
    front = pareto(rows)
    for r in rows:
        r["pareto"] = r["setting"] in front
    plot(sc["name"], rows, out_dir / f"pareto_{sc['name']}.png")
    return rows


def measure(jr, scene, camera, settings, repeats):
    import equinox as eqx
    import jax

    from jaxrt.render import _cast, _dtype, _render

    dyn, static = eqx.partition(_cast((scene, camera), _dtype(settings)), eqx.is_array)
    t0 = time.perf_counter()
    f = jax.jit(lambda d: _render.__wrapped__(*eqx.combine(d, static), settings))
    f = f.lower(dyn).compile()
    compile_s = time.perf_counter() - t0
    img = f(dyn)
    img.rgb.block_until_ready()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f(dyn).rgb.block_until_ready()
        times.append(time.perf_counter() - t)
    return dict(render_ms=1e3 * float(np.median(times)), compile_s=compile_s, image=img)


def errors(img, ref_rgb, ref_depth, ref_hit):
    rgb = np.asarray(img.rgb, np.float64)
    diff = np.abs(rgb - ref_rgb)
    hit = (np.asarray(img.coverage) > 0.5) & ref_hit
    depth = np.asarray(img.depth, np.float64)
    rel = np.abs(depth - ref_depth)[hit] / np.maximum(ref_depth[hit], 1e-12)
    return dict(rmse=float(np.sqrt(np.mean(diff ** 2))), max=float(diff.max()),
                depth_rel=float(np.median(rel)) if rel.size else float("nan"),
                finite=bool(np.isfinite(rgb).all()))


def pareto(rows):
    """Labels of the rows that no other row beats in both time and RMSE."""
    front = []
    for r in rows:
        dominated = any((o["render_ms"] <= r["render_ms"] and o["rmse"] <= r["rmse"]) and
                        (o["render_ms"] < r["render_ms"] or o["rmse"] < r["rmse"]) for o in rows)
        if not dominated:
            front.append(r["setting"])
    return front


def plot(name, rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    dials = sorted({r["dial"] for r in rows})
    cmap = plt.get_cmap("tab20")
    for i, d in enumerate(dials):
        pts = [r for r in rows if r["dial"] == d]
        ax.scatter([r["render_ms"] for r in pts], [max(r["rmse"], 1e-9) for r in pts],
                   color=cmap(i % 20), label=d, s=60 if d == "combo" else 25,
                   marker="*" if d == "combo" else "o", zorder=3)
    front = sorted((r for r in rows if r["pareto"]), key=lambda r: r["render_ms"])
    ax.plot([r["render_ms"] for r in front], [max(r["rmse"], 1e-9) for r in front], "k--",
            lw=1, label="Pareto front", zorder=2)
    for r in rows:
        if r["pareto"] or r["dial"] == "combo":
            ax.annotate(r["setting"], (r["render_ms"], max(r["rmse"], 1e-9)), fontsize=7,
                        xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("render time [ms] (median, after compilation)")
    ax.set_ylabel("RMSE of linear RGB against the reference")
    ax.set_title(f"{name}: speed against accuracy")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _markdown(sc, rows):
    lines = [f"## {sc['name']} ({sc['width']}×{sc['height']})", "",
             f"![{sc['name']}](pareto_{sc['name']}.png)", "",
             "| setting | render ms | compile s | RMSE | max | depth rel | front |",
             "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: r["render_ms"]):
        lines.append(f"| {r['setting']} | {r['render_ms']:.1f} | {r['compile_s']:.1f} | "
                     f"{r['rmse']:.2e} | {r['max']:.2e} | {r['depth_rel']:.1e} | "
                     f"{'●' if r['pareto'] else ''} |")
    return lines + [""]


if __name__ == "__main__":
    main()
