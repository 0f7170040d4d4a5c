"""Counts of image artefacts on a rendered `Image` (tests/test_shipped_scenes.py):

- NaN pixels: any channel of rgb not finite.
- black speckles: pixels that the *shadows* made much darker than all the hit pixels
  around them. A dark outlier is a hit pixel whose luminance Y is below `SPECKLE_RATIO`
  × the smallest luminance m of its hit 8-neighbours (at least 6 of them hit, and m
  above `SPECKLE_FLOOR`, so dark regions do not count); against the median instead,
  the dark rims along every outline of the showcase, a few pixels wide, counted (183 at
  192×108). Shadow acne and wrong occlusion darken a pixel by taking light away from
  it, so with a reference render of the same view with `shadows="none"` (radiance Y₀,
  the same scene, camera and settings otherwise) a speckle is a dark outlier that

      is no dark outlier in the reference (Y₀ ≥ SPECKLE_RATIO · m₀)  and
      keeps less than `SPECKLE_KEEP` of its unshadowed radiance (Y < SPECKLE_KEEP · Y₀):

  the shadow rays alone made it dark. A pixel that is a dark outlier without shadows
  too is dark by its shading (a glossy metal seen away from its lobe, a cavity facing
  away from the lights, a Whitted tree that ends while its rays are trapped in glass):
  its neighbours show a different surface or lobe, so they cannot tell whether its
  shadows are right, and it is counted apart (`dark_shading`), for a per-pixel trace
  (experiments/artefacts/trace_pixel.py) to judge. Without a reference every dark
  outlier counts.
- outline holes: a pixel that shows the background (its depth is the miss distance)
  although at least 3 of its 4-neighbours hit, and a reference render of the same
  view (more steps, or supersampled) hits there: not a real gap, a camera ray that ran
  out of budget crawling past a silhouette.
- see-through pixels: a pixel whose camera ray ran out of budget (its steps AOV above
  max_steps) and whose depth lies beyond the reference's (by more than
  `SEE_THROUGH_RTOL`): it shows the background or a surface behind the one the
  reference hits (before issue 14's fix, an exhausted ray that `integrator._meet_planes`
  carried on to the floor plane, through what lies between; now such a ray stays a
  miss, which still counts here where the reference hits). A hole that the outline test misses (its
  neighbours need not hit) is one of these.

Everything here is numpy on the rendered arrays.
"""

import numpy as np

#: A dark outlier is darker than this fraction of the darkest of its hit neighbours.
SPECKLE_RATIO = 0.2
#: ... and those neighbours are brighter than this (dark regions are not judged).
SPECKLE_FLOOR = 0.05
#: A speckle keeps less than this fraction of its radiance without shadows: shadow acne
#: takes (nearly) all of a light away; a pixel that keeps more is darkened by its
#: shading, not by its shadow rays.
SPECKLE_KEEP = 0.5
#: A see-through pixel's depth exceeds the reference's by more than this, relatively
#: (the same hit polished from another marched t differs by ~ε/t, far less).
SEE_THROUGH_RTOL = 1e-3
_LUMA = np.array([0.2126, 0.7152, 0.0722])


def luminance(rgb):
    return np.asarray(rgb, np.float64) @ _LUMA


def _neighbours(a, offsets, fill):
    """[len(offsets), H, W]: a shifted by each (dy, dx), `fill` outside the image."""
    h, w = a.shape
    padded = np.full((h + 2, w + 2), fill, dtype=a.dtype)
    padded[1:-1, 1:-1] = a
    return np.stack([padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy, dx in offsets])


_EIGHT = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]
_FOUR = [(-1, 0), (1, 0), (0, -1), (0, 1)]


def hit_mask(depth, max_distance):
    """Pixels whose primary ray hit (depth below the miss distance)."""
    d = np.asarray(depth, np.float64)
    return np.isfinite(d) & (d < 0.999 * max_distance)


def nan_pixels(rgb):
    return ~np.all(np.isfinite(np.asarray(rgb)), axis=-1)


def dark_outliers(rgb, hit):
    """Hit pixels darker than SPECKLE_RATIO × the darkest of their hit 8-neighbours (at
    least 6 of them hit, that darkest above SPECKLE_FLOOR)."""
    lum = luminance(rgb)
    lum = np.where(np.isfinite(lum), lum, 0.0)
    vals = _neighbours(np.where(hit, lum, np.nan), _EIGHT, np.nan)
    n_hit = np.sum(np.isfinite(vals), axis=0)
    darkest = np.min(np.where(np.isfinite(vals), vals, np.inf), axis=0)
    darkest = np.where(np.isfinite(darkest), darkest, 0.0)
    return hit & (n_hit >= 6) & (darkest > SPECKLE_FLOOR) & (lum < SPECKLE_RATIO * darkest)


def speckle_pixels(rgb, hit, unshadowed=None):
    """Black speckles: `dark_outliers` of `rgb`; with `unshadowed`, the rgb of the same
    view rendered with shadows="none", only those that are no dark outliers there and
    keep less than SPECKLE_KEEP of its luminance (see the module docstring)."""
    dark = dark_outliers(rgb, hit)
    if unshadowed is None:
        return dark
    keeps = luminance(rgb) < SPECKLE_KEEP * luminance(unshadowed)
    return dark & keeps & ~dark_outliers(unshadowed, hit)


def shading_dark_pixels(rgb, hit, unshadowed):
    """Dark outliers of `rgb` that are dark outliers of the unshadowed render too: dark
    by their shading, which their neighbours cannot judge (not speckles)."""
    return dark_outliers(rgb, hit) & dark_outliers(unshadowed, hit)


def outline_candidates(hit):
    """Missed pixels with at least 3 of their 4-neighbours hit."""
    around = _neighbours(hit.astype(np.int8), _FOUR, 0).sum(axis=0)
    return (~hit) & (around >= 3)


def hole_pixels(hit, reference_hit):
    """Outline candidates where the reference render hits: not real gaps."""
    return outline_candidates(hit) & reference_hit


def see_through_pixels(depth, reference_depth, exhausted):
    """Pixels whose camera ray ran out of budget (`exhausted`) and that see farther than
    the reference: depth > (1 + SEE_THROUGH_RTOL) · reference depth."""
    depth, reference_depth = np.asarray(depth, np.float64), np.asarray(reference_depth, np.float64)
    return np.asarray(exhausted) & (depth > (1.0 + SEE_THROUGH_RTOL) * reference_depth)


def counts(image, max_distance, reference=None, unshadowed=None, max_steps=None):
    """{"nan", "speckles", "dark_outliers", "outline_candidates"} of an `Image` (its
    depth AOV), with "holes" if `reference` (an `Image` of the same view with more steps
    or samples) is given, "see_through" if also `max_steps` and the image's steps AOV
    are, and "dark_shading" if `unshadowed` (the rgb, or an `Image`, of the same view
    with shadows="none") is: speckles are then judged against it."""
    hit = hit_mask(image.depth, max_distance)
    flat = getattr(unshadowed, "rgb", unshadowed)
    out = dict(nan=int(nan_pixels(image.rgb).sum()),
               speckles=int(speckle_pixels(image.rgb, hit, flat).sum()),
               dark_outliers=int(dark_outliers(image.rgb, hit).sum()))
    if flat is not None:
        out["dark_shading"] = int(shading_dark_pixels(image.rgb, hit, flat).sum())
    if reference is not None:
        out["holes"] = int(hole_pixels(hit, hit_mask(reference.depth, max_distance)).sum())
        if max_steps is not None and getattr(image, "steps", None) is not None:
            exhausted = np.asarray(image.steps) > max_steps
            out["see_through"] = int(see_through_pixels(image.depth, reference.depth, exhausted).sum())
    out["outline_candidates"] = int(outline_candidates(hit).sum())
    return out
