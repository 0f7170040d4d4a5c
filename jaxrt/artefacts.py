"""Counts of image artefacts on a rendered `Image` (tests/test_shipped_scenes.py):

- NaN pixels: any channel of rgb not finite.
- black speckles: a hit pixel much darker than all the hit pixels around it: its
  luminance below `SPECKLE_RATIO` × the smallest luminance of its hit 8-neighbours (at
  least 6 of them hit, and that smallest above `SPECKLE_FLOOR`, so dark regions do not
  count). Shadow acne shows as such pixels. (Against the median instead, the dark rims
  along every outline of the showcase, a few pixels wide, counted: 183 at 192×108.)
- outline holes: a pixel that shows the background (its depth is the miss distance)
  although at least 3 of its 4-neighbours hit, and a reference render of the same
  view (more steps, or supersampled) hits there: not a real gap, a camera ray that ran
  out of budget crawling past a silhouette.

Everything here is numpy on the rendered arrays.
"""

import numpy as np

SPECKLE_RATIO = 0.2
SPECKLE_FLOOR = 0.05
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


def speckle_pixels(rgb, hit):
    lum = luminance(rgb)
    lum = np.where(np.isfinite(lum), lum, 0.0)
    vals = _neighbours(np.where(hit, lum, np.nan), _EIGHT, np.nan)
    n_hit = np.sum(np.isfinite(vals), axis=0)
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmin(vals, axis=0)
    med = np.where(np.isfinite(med), med, 0.0)
    return hit & (n_hit >= 6) & (med > SPECKLE_FLOOR) & (lum < SPECKLE_RATIO * med)


def outline_candidates(hit):
    """Missed pixels with at least 3 of their 4-neighbours hit."""
    around = _neighbours(hit.astype(np.int8), _FOUR, 0).sum(axis=0)
    return (~hit) & (around >= 3)


def hole_pixels(hit, reference_hit):
    """Outline candidates where the reference render hits: not real gaps."""
    return outline_candidates(hit) & reference_hit


def counts(image, max_distance, reference=None):
    """{"nan", "speckles", "holes", "exhausted"} of an `Image` (depth and steps AOVs)."""
    hit = hit_mask(image.depth, max_distance)
    out = dict(nan=int(nan_pixels(image.rgb).sum()), speckles=int(speckle_pixels(image.rgb, hit).sum()))
    if reference is not None:
        out["holes"] = int(hole_pixels(hit, hit_mask(reference.depth, max_distance)).sum())
    out["outline_candidates"] = int(outline_candidates(hit).sum())
    return out
