"""Gather the studies' results into docs/inverse.md and docs/inverse/*.png.

    python experiments/inverse/report.py [--results results/inverse] [--docs docs]

For each study folder with a results.json (csg, materials, optics, pose): its table
(results.md), its command, machine and time, and its figures copied to
docs/inverse/<study>_grid.png and <study>_curves.png. The text around them is
INTRO and NOTES below (what each study is, and what its figures say).
"""

import argparse
import json
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
STUDIES = ("csg", "materials", "optics", "pose")

INTRO = """# Inverse rendering: studies

Each study is one script in `experiments/inverse/` reading
`configs/experiments/inverse_<name>.toml`; `--quick` runs its small version (the slow
tests in `tests/test_inverse_studies.py` run those and assert their quick targets).
They share `experiments/inverse/common.py`: targets rendered with point sampling at 16
spp and `silhouette=False` (the box-filtered truth), a start with every parameter moved
by up to 10 % (fixed seed), an Adam fit (`jaxrt.fit.adam`, cosine schedule, per-group
learning rates, legal values through `jaxrt.fit` transforms) of the L2 image loss over
all views (`jaxrt.render_views`, one compiled program), checkpointed. Errors are
|fit − truth| / max(|truth|, floor), floor 0 except for positions (a length, given in
each config). "loss at the truth" is the fit's loss at the true values: non-zero is the
estimator's bias (spp 1 and the silhouette term's dilation against the box-filtered
target); `fit.debias = true` removes it from the fixed point with a straight-through
loss (values of the target's estimator, gradients of the fit's).

To regenerate this page after running the studies:
`python experiments/inverse/report.py`.
"""

NOTES = {
    "csg": "CSG recovery: 8 primitives (round box, two spheres, capsule, cylinder, torus on a "
           "rotation, ellipsoid, box) in three smooth unions and a union, two materials "
           "(Lambert; GGX Cook–Torrance over a diffuse base), every shape and material "
           "parameter free (the torus's rotation axis, a direction, is fixed; its angle is free).",
    "materials": "Materials under known geometry: a Lambert sphere, a GGX/Schlick sphere over a "
                 "diffuse base, a rough conductor (GGX, η and κ per channel), three floor tiles "
                 "of their own albedo (a spatially varying albedo; the fourth is a grey card of "
                 "known albedo, which fixes the scale shared by intensities and reflectances), "
                 "and both lights' RGB intensities.",
    "optics": "Optics: a glass sphere in front of a sine-displaced wall lit from the side; the "
              "constant η (RGB rendering) or the Cauchy a, b (spectral rendering).",
    "pose": "Pose: the camera's eye and look-at point from one image of the CSG shape on a "
            "textured floor; orientation error is the angle between the fitted and true "
            "camera frames, position error relative to the camera's distance.",
}


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--results", default=str(ROOT / "results" / "inverse"))
    p.add_argument("--docs", default=str(ROOT / "docs"))
    a = p.parse_args(argv)
    results, docs = Path(a.results), Path(a.docs)
    (docs / "inverse").mkdir(parents=True, exist_ok=True)
    parts = [INTRO]
    for name in STUDIES:
        folder = results / name
        if not (folder / "results.json").is_file():
            continue
        r = json.loads((folder / "results.json").read_text())
        for fig in ("grid", "curves"):
            shutil.copyfile(folder / f"{fig}.png", docs / "inverse" / f"{name}_{fig}.png")
        m = r["machine"]
        cmd = f"python experiments/inverse/{name}.py" + (" --quick" if r["quick"] else "")
        parts += [f"## {name}", "", NOTES[name], "",
                  f"Command: `{cmd}`; machine: {m['device']} ({m['backend']}, {m['cpu_count']} CPUs, "
                  f"{m['platform']}); time: {r['seconds']['total']} s.", "",
                  "\n".join((folder / "results.md").read_text().splitlines()[2:]), "",
                  f"![{name}: target | start | fit | error](inverse/{name}_grid.png)", "",
                  f"![{name}: loss and parameter errors](inverse/{name}_curves.png)", ""]
    (docs / "inverse.md").write_text("\n".join(parts))
    print(f"wrote {docs / 'inverse.md'}")


if __name__ == "__main__":
    main()
