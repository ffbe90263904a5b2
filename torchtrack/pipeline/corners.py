"""Shi–Tomasi corners (``cv2.goodFeaturesToTrack``) of a frame computed over bands of rows, so that the
float32 images it needs (derivatives, their products, the eigenvalues: about 24 bytes per pixel) hold one band
instead of the frame: 385 MB at 4096², 1.6 GB at 66 megapixels.

OpenCV's selection, done here on bands of :data:`BAND_ROWS` rows (each computed from the band and
:data:`BAND_HALO` rows either side, more than the 3×3 derivative and the ``block × block`` window reach):

1. ``λ(x)``, the smaller eigenvalue of the gradients' covariance over the window (``cv2.cornerMinEigenVal``,
   3×3 Sobel);
2. a pixel off the frame's border is a candidate where ``λ > float32(quality · max λ)`` (the largest over
   the whole frame: a first pass over the bands) and ``λ`` equals the maximum of its 3×3 neighbourhood;
3. candidates in decreasing ``λ`` (equal values: the later pixel in raster order first), each kept unless a kept
   one lies closer than ``min_distance``, until ``count`` are kept.

Equal to ``cv2.goodFeaturesToTrack`` up to float rounding: OpenCV's window sums run down the image, so a band
rounds a few eigenvalues differently in the last bit (73 of 16.7 million at 4096²); a selection changes only
where such a value ties with another at the threshold, the 3×3 test or the cut. Checked to be identical on
the synthetic frames of the tests and of ``bench scale --frame-sizes`` (512² to 4096²).
"""

from __future__ import annotations

import cv2
import numpy as np

BAND_ROWS = 256
"""Rows per band."""

BAND_HALO = 8
"""Rows read beyond each side of a band: at least the Sobel's 1, the window's ``block // 2`` and the 3×3 test's 1."""


def _bands(image: np.ndarray, block: int):
    """Per band ``(y0, y1)``: its eigenvalues with one row beyond each edge where the frame has one, and the
    row of ``y0`` among them."""
    h = image.shape[0]
    for y0 in range(0, h, BAND_ROWS):
        y1 = min(h, y0 + BAND_ROWS)
        a, b = max(0, y0 - BAND_HALO), min(h, y1 + BAND_HALO)
        eig = cv2.cornerMinEigenVal(image[a:b], block, ksize=3)
        lo, hi = max(0, y0 - 1), min(h, y1 + 1)
        yield (y0, y1), eig[lo - a: hi - a], y0 - lo


def good_features(image: np.ndarray, count: int, quality: float, min_distance: float,
                  block: int) -> np.ndarray:
    """The corners ``(K, 1, 2)`` float32 (x, y) of the grey uint8 ``image (H, W)``, as
    ``cv2.goodFeaturesToTrack(image, count, quality, min_distance, blockSize=block)`` gives them (module
    docstring)."""
    h, w = image.shape
    top = max(float(eig[r: r + y1 - y0].max()) for (y0, y1), eig, r in _bands(image, block))
    threshold = np.float32(top * quality)
    values, cells = [], []
    for (y0, y1), eig, r in _bands(image, block):
        peak = cv2.dilate(eig, None)                       # 3×3 maximum (rows beyond the frame: none)
        rows = range(max(y0, 1), min(y1, h - 1))
        inner = eig[r + rows.start - y0: r + rows.stop - y0, 1: w - 1]
        ok = (inner > threshold) & (inner == peak[r + rows.start - y0: r + rows.stop - y0, 1: w - 1])
        ys, xs = np.nonzero(ok)
        values.append(inner[ys, xs])
        cells.append((ys + rows.start) * w + xs + 1)
    value, cell = np.concatenate(values), np.concatenate(cells)
    order = np.lexsort((-cell, -value))                     # by λ descending, then the later pixel first
    cell = cell[order]
    size = round(min_distance)                             # grid of cells: a rival lies in the 3×3 cells around
    grid: dict[tuple[int, int], list[tuple[int, int]]] = {}
    kept: list[tuple[int, int]] = []
    limit = min_distance * min_distance
    for c in cell.tolist():
        y, x = divmod(c, w)
        gy, gx = y // size, x // size
        if any((x - px) ** 2 + (y - py) ** 2 < limit
               for yy in (gy - 1, gy, gy + 1) for xx in (gx - 1, gx, gx + 1) for px, py in grid.get((yy, xx), ())):
            continue
        grid.setdefault((gy, gx), []).append((x, y))
        kept.append((x, y))
        if len(kept) == count:
            break
    return np.asarray(kept, np.float32).reshape(-1, 1, 2)
