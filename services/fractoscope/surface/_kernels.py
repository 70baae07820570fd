"""Compiled inner loops of the areal parameters and their uncertainty (numba): one pass over a height map where numpy
would make several map-sized temporaries, which on a 4096² map cost more than the arithmetic.
Each kernel computes exactly what the numpy definition in its calling module states; rows are
split across threads (prange) and reduced in float64."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

# numba.njit's options, passed as **JIT_OPTIONS: typed Any, as njit's overloads type each apart.
JIT_OPTIONS: dict[str, Any] = {"cache": True, "nogil": True, "fastmath": False}
_JIT = JIT_OPTIONS


@numba.njit(parallel=True, **_JIT)
def finite_height_summary(z):
    """(count of finite heights, their mean, the highest, the lowest)."""
    rows, cols = z.shape
    sums = np.zeros(rows)
    counts = np.zeros(rows)
    highest = np.full(rows, -np.inf)
    lowest = np.full(rows, np.inf)
    for r in numba.prange(rows):
        total, count = 0.0, 0.0
        hi, lo = -np.inf, np.inf
        for c in range(cols):
            v = z[r, c]
            if np.isfinite(v):
                total += v
                count += 1.0
                hi = max(hi, v)
                lo = min(lo, v)
        sums[r], counts[r] = total, count
        highest[r], lowest[r] = hi, lo
    n = counts.sum()
    return n, sums.sum() / n, highest.max(), lowest.min()


@numba.njit(parallel=True, **_JIT)
def central_moments(z, mean):
    """Sums over the finite heights h = z - mean of |h|, h², h³, h⁴ and sign h, and max h, min h."""
    rows, cols = z.shape
    partial = np.zeros((rows, 5))
    highest = np.full(rows, -np.inf)
    lowest = np.full(rows, np.inf)
    for r in numba.prange(rows):
        a1 = a2 = a3 = a4 = signs = 0.0
        hi, lo = -np.inf, np.inf
        for c in range(cols):
            v = z[r, c]
            if np.isfinite(v):
                h = v - mean
                h2 = h * h
                a1 += abs(h)
                a2 += h2
                a3 += h2 * h
                a4 += h2 * h2
                signs += 1.0 if h > 0 else (-1.0 if h < 0 else 0.0)
                hi = max(hi, h)
                lo = min(lo, h)
        partial[r, 0], partial[r, 1], partial[r, 2], partial[r, 3], partial[r, 4] = a1, a2, a3, a4, signs
        highest[r], lowest[r] = hi, lo
    sums = partial.sum(axis=0)
    return sums[0], sums[1], sums[2], sums[3], sums[4], highest.max(), lowest.min()


@numba.njit(parallel=True, **_JIT)
def slope_sums(z, inverse_pixel):
    """For Sdq and Sdr: sums and counts of the squared finite-difference slopes along x (each
    row's neighbours) and y, and the sum and count over complete cells of the four corner terms
    sqrt(gx² + gy² + 1) (top and bottom x edge with left and right y edge)."""
    rows, cols = z.shape
    partial = np.zeros((rows, 6))
    for r in numba.prange(rows):
        sx = nx = sy = ny = cell = ncell = 0.0
        for c in range(cols):
            v = z[r, c]
            if c + 1 < cols:
                gx = (z[r, c + 1] - v) * inverse_pixel
                if np.isfinite(gx):
                    sx += gx * gx
                    nx += 1.0
            if r + 1 < rows:
                gy = (z[r + 1, c] - v) * inverse_pixel
                if np.isfinite(gy):
                    sy += gy * gy
                    ny += 1.0
                if c + 1 < cols:
                    top = (z[r, c + 1] - v) * inverse_pixel
                    bottom = (z[r + 1, c + 1] - z[r + 1, c]) * inverse_pixel
                    left = (z[r + 1, c] - v) * inverse_pixel
                    right = (z[r + 1, c + 1] - z[r, c + 1]) * inverse_pixel
                    corners = (
                        np.sqrt(top * top + left * left + 1.0)
                        + np.sqrt(top * top + right * right + 1.0)
                        + np.sqrt(bottom * bottom + left * left + 1.0)
                        + np.sqrt(bottom * bottom + right * right + 1.0)
                    )
                    if np.isfinite(corners):
                        cell += corners
                        ncell += 1.0
        partial[r, 0], partial[r, 1], partial[r, 2] = sx, nx, sy
        partial[r, 3], partial[r, 4], partial[r, 5] = ny, cell, ncell
    sums = partial.sum(axis=0)
    return sums[0], sums[1], sums[2], sums[3], sums[4], sums[5]


# Uncertainty: block sums of sigma times a parameter's derivative ##################################


@numba.njit(parallel=True, **_JIT)
def height_block_sums(z, sigma, mean, block):
    """Block sums (block x block pixels; the last blocks partial) of sigma·{1, h, h², h³, sign h}
    over the finite heights, h = z - mean: (5, block rows, block cols); and the sums of h², h³, h⁴
    and sign h over them, as `central_moments` has them."""
    rows, cols = z.shape
    out_rows, out_cols = (rows + block - 1) // block, (cols + block - 1) // block
    sums = np.zeros((5, out_rows, out_cols))
    partial = np.zeros((rows, 4))
    for br in numba.prange(out_rows):
        for r in range(br * block, min(rows, (br + 1) * block)):
            a2 = a3 = a4 = signs = 0.0
            for c in range(cols):
                v = z[r, c]
                if np.isfinite(v):
                    s = sigma[r, c]
                    h = v - mean
                    h2 = h * h
                    sign = 1.0 if h > 0 else (-1.0 if h < 0 else 0.0)
                    a2 += h2
                    a3 += h2 * h
                    a4 += h2 * h2
                    signs += sign
                    bc = c // block
                    sums[0, br, bc] += s
                    sums[1, br, bc] += s * h
                    sums[2, br, bc] += s * h * h
                    sums[3, br, bc] += s * h * h * h
                    sums[4, br, bc] += s * sign
            partial[r, 0], partial[r, 1], partial[r, 2], partial[r, 3] = a2, a3, a4, signs
    totals = partial.sum(axis=0)
    return sums, totals[0], totals[1], totals[2], totals[3]


@numba.njit(**_JIT)
def _material_class(h, class_heights):
    """The material-ratio class k of a height: class_heights (K + 1,) are the curve's heights at
    the classes' edges, decreasing, and class k holds heights in (class_heights[k + 1],
    class_heights[k]] (the last class also what lies lower)."""
    classes = class_heights.size - 1
    low, high = 0, classes
    while low < high:
        middle = (low + high) // 2
        if class_heights[middle + 1] >= h:
            low = middle + 1
        else:
            high = middle
    return min(low, classes - 1)


@numba.njit(parallel=True, **_JIT)
def material_classes(z, mean, class_heights):
    """Each pixel's material-ratio class (`_material_class` of h = z - mean; the class count where
    z is unknown), uint8, and how many finite heights fall in each class. The class is read from a
    table over equal height bins where a bin and its two neighbours hold no class edge (a class is
    monotonic in h, so both ends of the three bins bound it), else searched."""
    rows, cols = z.shape
    classes = class_heights.size - 1
    bins = 64 * classes
    low = class_heights[-1]
    width = (class_heights[0] - low) / bins
    table = np.full(bins, -1, dtype=np.int64)
    if width > 0:
        for b in range(bins):
            k = _material_class(low + (b - 1) * width, class_heights)
            if k == _material_class(low + (b + 2) * width, class_heights):
                table[b] = k
    out = np.empty((rows, cols), dtype=np.uint8)
    counts = np.zeros((rows, classes))
    for r in numba.prange(rows):
        for c in range(cols):
            v = z[r, c]
            if np.isfinite(v):
                h = v - mean
                b = int(np.floor((h - low) / width)) if width > 0 else -1
                k = table[b] if 0 <= b < bins else -1
                if k < 0:
                    k = _material_class(h, class_heights)
                out[r, c] = k
                counts[r, k] += 1.0
            else:
                out[r, c] = classes
    return out, counts.sum(axis=0)


@numba.njit(parallel=True, **_JIT)
def class_block_sums(classes, sigma, derivatives, block):
    """Block sums of sigma · derivatives[class, p] over the pixels of a class map
    (`material_classes`; classes past the last row of derivatives are unknown points). Returns
    (P, block rows, block cols), summed with the parameters last (each pixel adds to P adjacent
    values)."""
    rows, cols = classes.shape
    known, parameters = derivatives.shape
    out_rows, out_cols = (rows + block - 1) // block, (cols + block - 1) // block
    sums = np.zeros((out_rows, out_cols, parameters))
    for br in numba.prange(out_rows):
        for r in range(br * block, min(rows, (br + 1) * block)):
            for c in range(cols):
                k = classes[r, c]
                if k < known:
                    s = sigma[r, c]
                    bc = c // block
                    for p in range(parameters):
                        sums[br, bc, p] += s * derivatives[k, p]
    return np.ascontiguousarray(sums.transpose(2, 0, 1))


@numba.njit(parallel=True, **_JIT)
def slope_block_sums(z, sigma, inverse_pixel, block):
    """Block sums of sigma · dSdq/dz and sigma · dSdr/dz, each up to a factor known only once the
    whole map is summed, and those sums: Sdq = sqrt(Sx / Nx + Sy / Ny) over the squared slopes gx², gy²
    (`slope_sums`), so dSdq/dgx = gx / (Nx Sdq): returned are the block sums qx of sigma · gx /
    pixel and qy of sigma · gy / pixel; Sdr = 100 / (4 Ncells) · (sum over complete cells of the
    corner terms T = sqrt(gx² + gy² + 1)) less 100, dT/dgx = gx / T: returned is the block sum of
    sigma · sum(dT/dz), with the sum of dT/d ln(s) = (gx² + gy²) / T for heights scaled by s. A slope
    (z_end - z_start) / pixel passes d(term)/d(slope) / pixel to the block of its end and minus that
    to the block of its start, each times the pixel's sigma. Rows of blocks go in two interleaved
    passes, so that no two threads add to the same block (a cell reaches into the next row).
    Returns (qx, qy, block sums for Sdr, their scale sum, Sx, Nx, Sy, Ny, Ncells)."""
    rows, cols = z.shape
    out_rows, out_cols = (rows + block - 1) // block, (cols + block - 1) // block
    qx = np.zeros((out_rows, out_cols))
    qy = np.zeros((out_rows, out_cols))
    dr = np.zeros((out_rows, out_cols))
    partial = np.zeros((rows, 6))
    for parity in range(2):
        for br in numba.prange(out_rows):
            if br % 2 != parity:
                continue
            for r in range(br * block, min(rows, (br + 1) * block)):
                total, sx, nx, sy, ny, cells = _slope_row_sums(z, sigma, inverse_pixel, block, r, qx, qy, dr)
                partial[r, 0], partial[r, 1], partial[r, 2] = total, sx, nx
                partial[r, 3], partial[r, 4], partial[r, 5] = sy, ny, cells
    sums = partial.sum(axis=0)
    return qx, qy, dr, sums[0], sums[1], sums[2], sums[3], sums[4], sums[5]


# inline="always" (numba's own inlining, here and in the two helpers below): left to LLVM the calls stay
# calls, and slope_block_sums takes 1.7 times as long.
@numba.njit(inline="always", **_JIT)
def _slope_row_sums(z, sigma, inverse_pixel, block, r, qx, qy, dr):
    """Row r's share of `slope_block_sums`: adds to the block sums qx, qy and dr (out_rows,
    out_cols) what its x slopes, its y slopes down to row r + 1 and the cells below it pass on,
    and returns its (scale sum, Sx, Nx, Sy, Ny, Ncells)."""
    rows, cols = z.shape
    br, below = r // block, (r + 1) // block
    total = sx = nx = sy = ny = cells = 0.0
    for c in range(cols):
        v = z[r, c]
        here, right_block = c // block, (c + 1) // block
        if c + 1 < cols:
            gx = (z[r, c + 1] - v) * inverse_pixel
            if np.isfinite(gx):
                sx += gx * gx
                nx += 1.0
                _pass_to_ends(qx, br, right_block, br, here, gx * inverse_pixel, sigma[r, c + 1], sigma[r, c])
        if r + 1 >= rows:
            continue
        gy = (z[r + 1, c] - v) * inverse_pixel
        if np.isfinite(gy):
            sy += gy * gy
            ny += 1.0
            _pass_to_ends(qy, below, here, br, here, gy * inverse_pixel, sigma[r + 1, c], sigma[r, c])
        if c + 1 >= cols:
            continue
        complete, scale = _cell_area_sums(z, sigma, inverse_pixel, r, c, gy, br, below, here, right_block, dr)
        if complete:
            cells += 1.0
            total += scale
    return total, sx, nx, sy, ny, cells


@numba.njit(inline="always", **_JIT)
def _cell_area_sums(z, sigma, inverse_pixel, r, c, left, br, below, here, right_block, dr):
    """Sdr's share of the cell with top-left pixel (r, c) (rows in block rows br and below, columns
    in block columns here and right_block; ``left`` its y slope at column c): adds sigma · dT/dz of
    its four corner terms to the block sums dr and returns (whether its four edge slopes are
    finite, its sum of dT/d ln(s)); a cell with an unknown corner adds nothing."""
    top = (z[r, c + 1] - z[r, c]) * inverse_pixel
    bottom = (z[r + 1, c + 1] - z[r + 1, c]) * inverse_pixel
    right = (z[r + 1, c + 1] - z[r, c + 1]) * inverse_pixel
    if not (np.isfinite(top) and np.isfinite(bottom) and np.isfinite(left) and np.isfinite(right)):
        return False, 0.0
    t_tl = 1.0 / np.sqrt(top * top + left * left + 1.0)
    t_tr = 1.0 / np.sqrt(top * top + right * right + 1.0)
    t_bl = 1.0 / np.sqrt(bottom * bottom + left * left + 1.0)
    t_br = 1.0 / np.sqrt(bottom * bottom + right * right + 1.0)
    d = inverse_pixel * top * (t_tl + t_tr)  # x edge (r, c) -> (r, c + 1)
    _pass_to_ends(dr, br, right_block, br, here, d, sigma[r, c + 1], sigma[r, c])
    d = inverse_pixel * bottom * (t_bl + t_br)  # x edge (r + 1, c) -> (r + 1, c + 1)
    _pass_to_ends(dr, below, right_block, below, here, d, sigma[r + 1, c + 1], sigma[r + 1, c])
    d = inverse_pixel * left * (t_tl + t_bl)  # y edge (r, c) -> (r + 1, c)
    _pass_to_ends(dr, below, here, br, here, d, sigma[r + 1, c], sigma[r, c])
    d = inverse_pixel * right * (t_tr + t_br)  # y edge (r, c + 1) -> (r + 1, c + 1)
    _pass_to_ends(dr, below, right_block, br, right_block, d, sigma[r + 1, c + 1], sigma[r, c + 1])
    scale = (
        (top * top + left * left) * t_tl
        + (top * top + right * right) * t_tr
        + (bottom * bottom + left * left) * t_bl
        + (bottom * bottom + right * right) * t_br
    )
    return True, scale


@numba.njit(inline="always", **_JIT)
def _pass_to_ends(sums, end_row, end_col, start_row, start_col, d, sigma_end, sigma_start):
    """A slope's share of the block sums: d (its term's derivative / pixel) times the sigma of its
    end pixel to the block of its end, minus d times that of its start to the block of its start."""
    sums[end_row, end_col] += d * sigma_end
    sums[start_row, start_col] -= d * sigma_start


# Feature parameters: steepest-ascent watershed ######################################################


@numba.njit(parallel=True, **_JIT)
def centred_heights(z, mean):
    """z - mean, -inf where z is unknown (the watershed's heights)."""
    rows, cols = z.shape
    out = np.empty((rows, cols))
    for r in numba.prange(rows):
        for c in range(cols):
            v = z[r, c]
            out[r, c] = v - mean if np.isfinite(v) else -np.inf
    return out


@numba.njit(parallel=True, **_JIT)
def labels_at_gaps(labels, heights, count):
    """Which labels (count + 1,) reach the field's border or an unknown point (height -inf): labels
    of the border pixels and of scipy.ndimage.binary_dilation(unknown), the unknown pixels and their
    4 neighbours. Threads may mark a label twice, always alike."""
    rows, cols = labels.shape
    touching = np.zeros(count + 1, dtype=np.bool_)
    for r in numba.prange(rows):
        for c in range(cols):
            if r == 0 or r == rows - 1 or c == 0 or c == cols - 1:
                touching[labels[r, c]] = True
            if heights[r, c] == -np.inf:
                touching[labels[r, c]] = True
                if r > 0:
                    touching[labels[r - 1, c]] = True
                if r + 1 < rows:
                    touching[labels[r + 1, c]] = True
                if c > 0:
                    touching[labels[r, c - 1]] = True
                if c + 1 < cols:
                    touching[labels[r, c + 1]] = True
    return touching


@numba.njit(parallel=True, **_JIT)
def _ascent_targets(heights, target):
    """Each pixel's (flat) steepest-ascent neighbour into target (rows * cols,): the highest of its
    eight, the first in row-major order on ties; itself where none is higher."""
    rows, cols = heights.shape
    for r in numba.prange(rows):
        for c in range(cols):
            inside = 0 < r < rows - 1 and 0 < c < cols - 1  # no neighbour off the map
            best, chosen = -np.inf, r * cols + c
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    rr, cc = r + dr, c + dc
                    if (
                        (dr != 0 or dc != 0)
                        and (inside or (0 <= rr < rows and 0 <= cc < cols))
                        and heights[rr, cc] > best
                    ):
                        best, chosen = heights[rr, cc], rr * cols + cc
            target[r * cols + c] = chosen if best > heights[r, c] else r * cols + c
    return target


@numba.njit(**_JIT)
def ascent_labels(heights, labels):
    """Label each pixel 1..n with the local maximum (plateau: an 8-connected set of pixels none of
    whose neighbours is higher) that steepest ascent reaches from it; the steepest neighbour is the
    highest, the first in row-major neighbour order on ties. ``labels``: (rows * cols,) zeros of
    an integer type that holds rows * cols (int32 where it does: half the memory traffic of the
    walks). Returns (labels (rows, cols), flat index of the last pixel, row-major, of each label's
    maximum; index 0 unused)."""
    rows, cols = heights.shape
    n = rows * cols
    target = _ascent_targets(heights, np.empty_like(labels))
    # Plateaus (pixels that do not climb) are labelled by an 8-connected flood fill.
    stack = np.empty(n, dtype=np.int64)
    peaks = [0]
    count = 0
    for start in range(n):
        if target[start] != start or labels[start] != 0:
            continue
        count += 1
        peaks.append(start)
        labels[start] = count
        top = 0
        stack[0] = start
        while top >= 0:
            p = stack[top]
            top -= 1
            peaks[count] = max(peaks[count], p)  # the plateau's last pixel in row-major order
            r, c = p // cols, p % cols
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < rows and 0 <= cc < cols:
                        q = rr * cols + cc
                        if labels[q] == 0 and target[q] == q:
                            labels[q] = count
                            top += 1
                            stack[top] = q
    _climb(target, labels, rows, cols)
    return labels.reshape(rows, cols), np.array(peaks, dtype=np.int64)


@numba.njit(parallel=True, **_JIT)
def _climb(target, labels, rows, cols):
    """Every unlabelled pixel takes the label its ascent ends at, and so does each pixel on the way
    (the walks of later pixels stop there). Threads may label a pixel twice, always alike."""
    for r in numba.prange(rows):
        for start in range(r * cols, (r + 1) * cols):
            p = start
            while labels[p] == 0:
                p = target[p]
            label = labels[p]
            p = start
            while labels[p] == 0:
                labels[p] = label
                p = target[p]


@numba.njit(**_JIT)
def hill_boundaries(labels, heights):
    """Adjacent hill pairs across every 8-connected boundary (right, down, down-right, down-left
    neighbours): (low label, high label, pass height = the lower of the two heights). A pair met
    again while it is still in a small hashed cache of recent pairs (most repeats are a row or
    two apart) is folded into its entry, keeping the largest pass; the rest are new entries."""
    rows, cols = labels.shape
    capacity = 1024
    low = np.empty(capacity, dtype=np.int64)
    high = np.empty(capacity, dtype=np.int64)
    value = np.empty(capacity)
    size = 0
    slots = 1 << 14
    cached = np.full(slots, -1, dtype=np.int64)  # entry of the pair last hashed to each slot
    for r in range(rows):
        for c in range(cols):
            a = labels[r, c]
            right, down = c + 1 < cols, r + 1 < rows
            if (not right or labels[r, c + 1] == a) and (
                not down
                or (
                    labels[r + 1, c] == a
                    and (not right or labels[r + 1, c + 1] == a)
                    and (c == 0 or labels[r + 1, c - 1] == a)
                )
            ):
                continue  # inside a hill, as most pixels are
            for k in range(4):
                rr, cc = (
                    (r, c + 1) if k == 0 else ((r + 1, c) if k == 1 else ((r + 1, c + 1) if k == 2 else (r + 1, c - 1)))
                )
                if rr >= rows or cc < 0 or cc >= cols:
                    continue
                b = labels[rr, cc]
                if a == b:
                    continue
                lo_label, hi_label = (a, b) if a < b else (b, a)
                height = min(heights[r, c], heights[rr, cc])
                slot = (lo_label * 40503 + hi_label) & (slots - 1)
                entry = cached[slot]
                if entry >= 0 and low[entry] == lo_label and high[entry] == hi_label:
                    value[entry] = max(value[entry], height)
                    continue
                if size == capacity:
                    capacity *= 2
                    low = np.resize(low, capacity)
                    high = np.resize(high, capacity)
                    value = np.resize(value, capacity)
                low[size], high[size], value[size] = lo_label, hi_label, height
                cached[slot] = size
                size += 1
    return low[:size].copy(), high[:size].copy(), value[:size].copy()


@numba.njit(parallel=True, **_JIT)
def sigma_statistics(z, sigma):
    """Whether sigma is finite and >= 0 wherever z is finite, its mean square there, and the flat
    indices of the highest and the lowest finite height (the first in row-major order on ties, as
    np.argmax and np.argmin)."""
    rows, cols = z.shape
    bad = np.zeros(rows)
    squares = np.zeros(rows)
    counts = np.zeros(rows)
    highest = np.full(rows, -np.inf)
    lowest = np.full(rows, np.inf)
    at_highest = np.zeros(rows, dtype=np.int64)
    at_lowest = np.zeros(rows, dtype=np.int64)
    for r in numba.prange(rows):
        for c in range(cols):
            v = z[r, c]
            if np.isfinite(v):
                if v > highest[r]:
                    highest[r], at_highest[r] = v, r * cols + c
                if v < lowest[r]:
                    lowest[r], at_lowest[r] = v, r * cols + c
                s = sigma[r, c]
                if not (np.isfinite(s) and s >= 0):
                    bad[r] = 1.0
                    continue
                squares[r] += s * s
                counts[r] += 1.0
    mean_square = squares.sum() / max(counts.sum(), 1.0)
    return bad.sum() == 0, mean_square, at_highest[np.argmax(highest)], at_lowest[np.argmin(lowest)]


@numba.njit(**_JIT)
def window_sum_squares(sums, m):
    """The sum over every position of an m x m window, on the grid padded by m - 1 zeros on each
    side, of the squared sum of the values under it (block grids are small: one thread)."""
    rows, cols = sums.shape
    padded = np.zeros((rows + 2 * (m - 1), cols + 2 * (m - 1)))
    padded[m - 1 : m - 1 + rows, m - 1 : m - 1 + cols] = sums
    out_rows, out_cols = rows + m - 1, cols + m - 1
    along = np.zeros((padded.shape[0], out_cols))
    for r in range(padded.shape[0]):
        for j in range(out_cols):
            total = 0.0
            for k in range(m):
                total += padded[r, j + k]
            along[r, j] = total
    result = 0.0
    for i in range(out_rows):
        for j in range(out_cols):
            total = 0.0
            for k in range(m):
                total += along[i + k, j]
            result += total * total
    return result


@numba.njit(parallel=True, **_JIT)
def height_histogram(z, mean, low, width, bins):
    """Counts of the finite heights h = z - mean in `bins` classes of `width` from `low` (the top
    class closed)."""
    rows, cols = z.shape
    chunks = min(rows, 8)
    counts = np.zeros((chunks, bins), dtype=np.int64)
    for chunk in numba.prange(chunks):
        for r in range(chunk * rows // chunks, (chunk + 1) * rows // chunks):
            for c in range(cols):
                v = z[r, c]
                if np.isfinite(v):
                    counts[chunk, min(int((v - mean - low) / width), bins - 1)] += 1
    return counts.sum(axis=0)
