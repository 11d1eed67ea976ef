"""OpenCV's polygon fill (`cv2.fillPoly`, 8-connected, no sub-pixel shift) in numpy, without OpenCV.

LangSplat's evaluation code turns each LERF-OVS polygon into its ground-truth mask with
``cv2.fillPoly(mask, [np.asarray(points, np.int32)], 1)``; OpenGaussian and the later LangSplat
derivatives copy it. A mask drawn by another fill rule moves every boundary pixel and so every IoU
(PIL's fill agreed with it at IoU 0.974-0.996; docs/evaluation.md). This module paints the same
pixels as OpenCV (tests/test_polyfill.py compares with masks cv2 drew, stored in tests/data, and
with cv2 itself when it is installed).

OpenCV's rule for one polygon with integer vertices v_0 .. v_{P-1} on an H x W image:

1. Outline: every edge v_{i-1} -> v_i (v_{-1} = v_{P-1}) is drawn as an 8-connected Bresenham
   line (`lines_pixels`), after clipping it to the image (`clip_segment`, Cohen-Sutherland in
   integers, divisions truncated toward zero as C's).
2. Interior: each non-horizontal edge covers the rows y0 <= y < y1 (its lower end excluded) with
   the fixed-point x = x0·2¹⁶ + (y - y0)·dx, dx = trunc((x1 - x0)·2¹⁶ / (y1 - y0)); an edge with
   an end outside the image takes x0 and dx from its clipped part (`polygon_edges`). On every row
   the covering edges are sorted by x and paired (even-odd); a pair paints
   ceil(x_left / 2¹⁶) .. floor(x_right / 2¹⁶) (`scanline_spans`). Fewer than two such edges fill
   nothing, nor does a polygon whose extent misses the image.

Both steps are whole-array numpy (no loop per pixel or per row; a Python loop only over the edges
that leave the image), in runs of edges and bands of rows of at most SPAN_ENTRIES pixels or
crossings, so a hostile polygon of 10⁵ vertices costs seconds and ~100 MB, not a mask per edge.

Integer vertices: LangSplat casts the float annotations with numpy's int32 cast (truncation
toward zero), which `truncate_vertices` repeats.
"""

from __future__ import annotations

import numpy as np

from drsplat.utils import concat_ranges

XY_SHIFT = 16  # OpenCV's fixed point for the edges' x (16 fractional bits)
XY_ONE = 1 << XY_SHIFT


def truncate_vertices(points: np.ndarray) -> np.ndarray:
    """[P, 2] float (x, y) -> [P, 2] int64, truncated toward zero like numpy's int32 cast
    (``np.asarray(points, np.int32)``, LangSplat's `polygon_to_mask`) for values within int32."""
    return np.trunc(np.asarray(points, np.float64).reshape(-1, 2)).astype(np.int64)


def trunc_div(num, den):
    """C's integer division, rounded toward zero (Python's // rounds down): Python ints or int64
    arrays; den != 0."""
    q = abs(num) // abs(den)
    if isinstance(q, np.ndarray):
        return np.where((num < 0) != (den < 0), -q, q)
    return -q if (num < 0) != (den < 0) else q


def clip_segment(p1: tuple[int, int], p2: tuple[int, int], width: int, height: int) -> tuple[bool, tuple[int, int], tuple[int, int]]:
    """OpenCV's `clipLine` of the segment p1 -> p2 to the pixels 0..W-1 x 0..H-1: (whether a part
    of it is inside, the moved ends). An end outside is moved along the segment to the nearest
    image row, then column, with C's truncating division; the ends come back moved even when no
    part is inside, as OpenCV leaves them (its fill uses them either way)."""
    right, bottom = width - 1, height - 1
    (x1, y1), (x2, y2) = (int(p1[0]), int(p1[1])), (int(p2[0]), int(p2[1]))
    if width <= 0 or height <= 0:
        return False, (x1, y1), (x2, y2)

    def code(x: int, y: int) -> int:
        return (x < 0) + (x > right) * 2 + (y < 0) * 4 + (y > bottom) * 8

    c1, c2 = code(x1, y1), code(x2, y2)
    if (c1 & c2) == 0 and (c1 | c2) != 0:
        if c1 & 12:
            a = 0 if c1 < 8 else bottom
            x1 += trunc_div((a - y1) * (x2 - x1), y2 - y1)
            y1 = a
            c1 = (x1 < 0) + (x1 > right) * 2
        if c2 & 12:
            a = 0 if c2 < 8 else bottom
            x2 += trunc_div((a - y2) * (x2 - x1), y2 - y1)
            y2 = a
            c2 = (x2 < 0) + (x2 > right) * 2
        if (c1 & c2) == 0 and (c1 | c2) != 0:
            if c1:
                a = 0 if c1 == 1 else right
                y1 += trunc_div((a - x1) * (y2 - y1), x2 - x1)
                x1 = a
                c1 = 0
            if c2:
                a = 0 if c2 == 1 else right
                y2 += trunc_div((a - x2) * (y2 - y1), x2 - x1)
                x2 = a
                c2 = 0
    return (c1 | c2) == 0, (x1, y1), (x2, y2)


def line_pixels_reference(p1: tuple[int, int], p2: tuple[int, int]) -> np.ndarray:
    """[dx + 1, 2] the (x, y) pixels of OpenCV's 8-connected line p1 -> p2 (already inside the
    image), one step at a time: err = dx - 2·dy; each step moves along the major axis, and along the
    minor one too when err < 0 (before the step); err += -2·dy (+ 2·dx when it moved)."""
    (x, y), end = p1, p2
    if end[0] < x:  # drawn left to right: the ends swap
        (x, y), end = end, (x, y)
    dx, dy = end[0] - x, end[1] - y
    step_y = -1 if dy < 0 else 1
    dy = abs(dy)
    vertical = dy > dx
    if vertical:
        dx, dy = dy, dx
    err = dx - 2 * dy
    out = []
    for _ in range(dx + 1):
        out.append((x, y))
        minor = err < 0
        err += -2 * dy + (2 * dx if minor else 0)
        if vertical:
            y += step_y
            x += 1 if minor else 0
        else:
            x += 1
            y += step_y if minor else 0
    return np.array(out, np.int64).reshape(-1, 2)


def line_pixels(p1: tuple[int, int], p2: tuple[int, int]) -> np.ndarray:
    """`line_pixels_reference` in closed form (`lines_pixels` of one line). [dx + 1, 2] int64 (x, y)."""
    return lines_pixels(np.array([[p1[0], p1[1], p2[0], p2[1]]], np.int64))


def lines_pixels(segments: np.ndarray) -> np.ndarray:
    """The pixels of many OpenCV lines at once: segments [L, 4] int64 (x1, y1, x2, y2), each already
    inside the image -> [Q, 2] int64 (x, y), line after line. After i steps a walk has moved
    m_i = floor((2·dy·i + dx - 1) / (2·dx)) times along its minor axis (the count of steps whose err
    was negative in `line_pixels_reference`), so every pixel comes from one arange."""
    seg = np.asarray(segments, np.int64).reshape(-1, 4)
    swap = seg[:, 2] < seg[:, 0]  # drawn left to right: the ends swap
    x = np.where(swap, seg[:, 2], seg[:, 0])
    y = np.where(swap, seg[:, 3], seg[:, 1])
    run = np.abs(seg[:, 2] - seg[:, 0])
    rise = np.where(swap, seg[:, 1] - seg[:, 3], seg[:, 3] - seg[:, 1])
    step_y = np.where(rise < 0, -1, 1)
    rise = np.abs(rise)
    vertical = rise > run
    major, minor_len = np.maximum(run, rise), np.minimum(run, rise)
    counts = major + 1
    line = np.repeat(np.arange(seg.shape[0]), counts)
    i = concat_ranges(np.zeros_like(counts), counts)
    big = np.maximum(major[line], 1)
    minor = np.where(major[line] > 0, (2 * minor_len[line] * i + big - 1) // (2 * big), 0)
    vert = vertical[line]
    px = x[line] + np.where(vert, minor, i)
    py = y[line] + step_y[line] * np.where(vert, i, minor)
    return np.stack([px, py], axis=1)


def polygon_segments(vertices: np.ndarray) -> np.ndarray:
    """[P, 4] int64 the closed polygon's edges (x1, y1, x2, y2), edge i running v_{i-1} -> v_i."""
    v = np.asarray(vertices, np.int64).reshape(-1, 2)
    return np.concatenate([np.roll(v, 1, axis=0), v], axis=1)


def clipped_segments(vertices: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The polygon's edges (`polygon_segments` [P, 4]), their ends after `clip_segment` [P, 4] (the
    edges within the image as they are) and [P] bool whether a part of each is inside: what both
    the outline and the interior of OpenCV's fill take from the clipping, made once."""
    seg = polygon_segments(vertices)
    ends = seg.copy()
    inside = np.ones(seg.shape[0], np.bool_)
    xs, ys = seg[:, 0::2], seg[:, 1::2]
    for e in np.flatnonzero(((xs < 0) | (xs >= width) | (ys < 0) | (ys >= height)).any(axis=1)):
        xa, ya, xb, yb = seg[e].tolist()
        inside[e], a, b = clip_segment((xa, ya), (xb, yb), width, height)
        ends[e] = (*a, *b)
    return seg, ends, inside


def polygon_edges(segments: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The non-horizontal edges of the closed polygon as OpenCV's CollectPolyEdges keeps them: rows
    y0 < y1 (the vertices' own), the fixed-point x at y0 and dx per row. An edge with an end outside
    the image takes its slope from the part `clip_segment` leaves (x of both clipped ends, and their
    rows unless the clipped part is level), extended back to row y0; dx is truncated toward zero.
    segments: `clipped_segments`. Returns four [E] int64."""
    seg, ends, _ = segments
    sloped = seg[:, 1] != seg[:, 3]
    seg, ends = seg[sloped], ends[sloped].copy()
    level = ends[:, 1] == ends[:, 3]  # clipped to a level part: OpenCV keeps the vertices' rows
    ends[level, 1], ends[level, 3] = seg[level, 1], seg[level, 3]
    xa_c, xb_c = ends[:, 0] << XY_SHIFT, ends[:, 2] << XY_SHIFT
    dx = trunc_div(xb_c - xa_c, ends[:, 3] - ends[:, 1])
    down = seg[:, 1] < seg[:, 3]
    y0 = np.where(down, seg[:, 1], seg[:, 3])
    y1 = np.where(down, seg[:, 3], seg[:, 1])
    x0 = np.where(down, xa_c + (seg[:, 1] - ends[:, 1]) * dx, xb_c + (seg[:, 3] - ends[:, 3]) * dx)
    return y0, y1, x0, dx


SPAN_ENTRIES = 1 << 22  # (edge, row) crossings made at once: a band of rows at a time beyond it (~100 MB of int64 arrays)


def _band_spans(y0: np.ndarray, y1: np.ndarray, x0: np.ndarray, dx: np.ndarray, lo: int, hi: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The spans of rows lo .. hi - 1: each row's edge crossings x = x0 + (y - y0)·dx sorted and
    paired (even-odd), a pair painting ceil(x_l / 2¹⁶) .. floor(x_r / 2¹⁶), clipped to the image."""
    first_row = np.clip(y0, lo, hi)
    counts = np.clip(y1, lo, hi) - first_row
    edge = np.repeat(np.arange(y0.size), counts)
    row = concat_ranges(first_row, counts)
    x = x0[edge] + (row - y0[edge]) * dx[edge]
    order = np.lexsort((x, row))
    row, x = row[order], x[order]
    # a closed polygon crosses every row's half-open band an even number of times, so pairs never straddle rows
    left, right, row = x[0::2], x[1::2], row[0::2]
    first = np.maximum((left + XY_ONE - 1) >> XY_SHIFT, 0)
    last = np.minimum(right >> XY_SHIFT, width - 1)
    keep = (first <= last) & (first < width) & (last >= 0)
    return row[keep], first[keep], last[keep]


def _runs(cumulative: np.ndarray, cap: int, longest: int | None = None):
    """Consecutive runs [lo, hi) of items whose sizes add up (cumulative [n], their running sum) to
    at most about `cap` each (an item is never split) and, with `longest`, of at most that many items."""
    lo, n = 0, cumulative.shape[0]
    while lo < n:
        done = cumulative[lo - 1] if lo > 0 else 0
        hi = max(lo + 1, int(np.searchsorted(cumulative, done + cap, side="right")))
        hi = min(hi, n, lo + longest) if longest else min(hi, n)
        yield lo, hi
        lo = hi


def scanline_spans(segments: tuple[np.ndarray, np.ndarray, np.ndarray], height: int, width: int, max_entries: int = SPAN_ENTRIES):
    """The interior of OpenCV's fill as row spans, in bands of rows holding at most about
    `max_entries` edge crossings (one row's crossings are never split) and `max_entries` pixels:
    yields (the band's first and end row, rows [S], first and last columns [S], inclusive, clipped
    to the image). segments: `clipped_segments`."""
    y0, y1, x0, dx = polygon_edges(segments)
    if y0.size < 2:
        return
    x_end = x0 + (y1 - y0) * dx
    if (y1.max() < 0 or y0.min() >= height or max(x0.max(), x_end.max()) < 0
            or min(x0.min(), x_end.min()) >= (width << XY_SHIFT)):
        return
    per_row = np.zeros(height + 1, np.int64)  # crossings per image row (rows above the image are never painted)
    np.add.at(per_row, np.clip(y0, 0, height), 1)
    np.add.at(per_row, np.clip(y1, 0, height), -1)
    for lo, hi in _runs(np.cumsum(np.cumsum(per_row)[:height]), max_entries, max(1, max_entries // (width + 1))):
        yield (lo, hi, *_band_spans(y0, y1, x0, dx, lo, hi, width))


def outline_pixels(segments: tuple[np.ndarray, np.ndarray, np.ndarray], max_pixels: int = SPAN_ENTRIES):
    """The polygon's edges as OpenCV draws them, each clipped to the image (`clipped_segments`);
    yields [Q, 2] int64 (x, y) pixels for runs of edges holding at most about `max_pixels` pixels
    (one edge is never split)."""
    _, ends, inside = segments
    ends = ends[inside]
    lengths = np.maximum(np.abs(ends[:, 2] - ends[:, 0]), np.abs(ends[:, 3] - ends[:, 1])) + 1
    for lo, hi in _runs(np.cumsum(lengths), max_pixels):
        yield lines_pixels(ends[lo:hi])


def fill_polygon(vertices: np.ndarray, height: int, width: int, max_entries: int = SPAN_ENTRIES) -> np.ndarray:
    """[H, W] bool: the pixels ``cv2.fillPoly(mask, [vertices], 1)`` paints (8-connected, shift 0).

    vertices: [P, 2] integer (x, y) pixel coordinates (`truncate_vertices` for float annotations),
    at most ~2²⁰ px outside the image (the fixed-point rows stay within int64); the math is in the
    module docstring. P = 0 paints nothing; P = 1 or 2 paints the outline only. max_entries: the
    most pixels, crossings or marks handled at once (memory, not the result, depends on it).
    """
    v = np.asarray(vertices, np.int64).reshape(-1, 2)
    mask = np.zeros((height, width), np.bool_)
    if v.shape[0] == 0 or height <= 0 or width <= 0:
        return mask
    segments = clipped_segments(v, height, width)
    for px in outline_pixels(segments, max_entries):
        mask[px[:, 1], px[:, 0]] = True
    for lo, hi, rows, first, last in scanline_spans(segments, height, width, max_entries):
        marks = np.zeros((hi - lo, width + 1), np.int32)  # +1 at a span's start, -1 past its end
        np.add.at(marks, (rows - lo, first), 1)
        np.add.at(marks, (rows - lo, last + 1), -1)
        mask[lo:hi] |= np.cumsum(marks, axis=1, dtype=np.int32)[:, :width] > 0
    return mask
