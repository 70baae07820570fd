"""Compiled inner loops of the surface analysis (numba): one pass over a height map where numpy
would make several map-sized temporaries, which on a 4096² map cost more than the arithmetic.
Each kernel computes exactly what the numpy definition in its calling module states; rows are
split across threads (prange) and reduced in float64."""

from __future__ import annotations

import numba
import numpy as np

_JIT = {"cache": True, "nogil": True, "fastmath": False}


@numba.njit(parallel=True, **_JIT)
def mean_height(z):
    """(count of finite heights, their mean)."""
    rows, cols = z.shape
    sums = np.zeros(rows)
    counts = np.zeros(rows)
    for r in numba.prange(rows):
        total, count = 0.0, 0.0
        for c in range(cols):
            v = z[r, c]
            if np.isfinite(v):
                total += v
                count += 1.0
        sums[r], counts[r] = total, count
    n = counts.sum()
    return n, sums.sum() / n


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
                        np.sqrt(top * top + left * left + 1.0) + np.sqrt(top * top + right * right + 1.0)
                        + np.sqrt(bottom * bottom + left * left + 1.0) + np.sqrt(bottom * bottom + right * right + 1.0)
                    )  # fmt: skip
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
    over the finite heights, h = z - mean: (5, block rows, block cols)."""
    rows, cols = z.shape
    out_rows, out_cols = (rows + block - 1) // block, (cols + block - 1) // block
    sums = np.zeros((5, out_rows, out_cols))
    for br in numba.prange(out_rows):
        for r in range(br * block, min(rows, (br + 1) * block)):
            for c in range(cols):
                v = z[r, c]
                if np.isfinite(v):
                    s = sigma[r, c]
                    h = v - mean
                    bc = c // block
                    sums[0, br, bc] += s
                    sums[1, br, bc] += s * h
                    sums[2, br, bc] += s * h * h
                    sums[3, br, bc] += s * h * h * h
                    sums[4, br, bc] += s * (1.0 if h > 0 else (-1.0 if h < 0 else 0.0))
    return sums


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


@numba.njit(**_JIT)
def class_counts(z, mean, class_heights):
    """How many finite heights (h = z - mean) fall in each material-ratio class."""
    rows, cols = z.shape
    counts = np.zeros(class_heights.size - 1)
    for r in range(rows):
        for c in range(cols):
            v = z[r, c]
            if np.isfinite(v):
                counts[_material_class(v - mean, class_heights)] += 1.0
    return counts


@numba.njit(parallel=True, **_JIT)
def class_block_sums(z, sigma, mean, class_heights, derivatives, block):
    """Block sums of sigma · derivatives[class, p] over the finite heights (h = z - mean), each in
    its material-ratio class (`_material_class`). Returns (P, block rows, block cols)."""
    rows, cols = z.shape
    parameters = derivatives.shape[1]
    out_rows, out_cols = (rows + block - 1) // block, (cols + block - 1) // block
    sums = np.zeros((parameters, out_rows, out_cols))
    for br in numba.prange(out_rows):
        for r in range(br * block, min(rows, (br + 1) * block)):
            for c in range(cols):
                v = z[r, c]
                if np.isfinite(v):
                    k = _material_class(v - mean, class_heights)
                    s = sigma[r, c]
                    bc = c // block
                    for p in range(parameters):
                        sums[p, br, bc] += s * derivatives[k, p]
    return sums


@numba.njit(parallel=True, **_JIT)
def slope_edge_derivatives(z, inverse_pixel, sdq_x_scale, sdq_y_scale, sdr_scale):
    """dSdq/d(slope) and dSdr/d(slope) of every x edge (rows, cols - 1) and y edge (rows - 1, cols),
    and d Sdr / d ln(s) for heights scaled by s. Sdq = sqrt(sum gx² / Nx + sum gy² / Ny), so
    dSdq/dgx = gx · sdq_x_scale (= 1 / (Nx Sdq)); Sdr = sdr_scale · sum over complete cells of the
    corner terms T = sqrt(gx² + gy² + 1) (sdr_scale = 100 / (4 N_cells)), dT/dgx = gx / T, and
    dT/d ln(s) = (gx² + gy²) / T. Edges of unknown slope get 0."""
    rows, cols = z.shape
    dq_x = np.zeros((rows, cols - 1), dtype=np.float32)
    dq_y = np.zeros((rows - 1, cols), dtype=np.float32)
    dr_x = np.zeros((rows, cols - 1), dtype=np.float32)
    dr_y = np.zeros((rows - 1, cols), dtype=np.float32)
    scale_terms = np.zeros(rows)
    for r in numba.prange(rows):
        for c in range(cols):
            v = z[r, c]
            if c + 1 < cols:
                gx = (z[r, c + 1] - v) * inverse_pixel
                if np.isfinite(gx):
                    dq_x[r, c] = gx * sdq_x_scale
            if r + 1 < rows:
                gy = (z[r + 1, c] - v) * inverse_pixel
                if np.isfinite(gy):
                    dq_y[r, c] = gy * sdq_y_scale
    # Rows of cells in two interleaved passes, so that no two threads write the same edge.
    for parity in range(2):
        for r in numba.prange(rows):
            if r % 2 != parity:
                continue
            total = 0.0
            for c in range(cols):
                v = z[r, c]
                if r + 1 < rows and c + 1 < cols:
                    top = (z[r, c + 1] - v) * inverse_pixel
                    bottom = (z[r + 1, c + 1] - z[r + 1, c]) * inverse_pixel
                    left = (z[r + 1, c] - v) * inverse_pixel
                    right = (z[r + 1, c + 1] - z[r, c + 1]) * inverse_pixel
                    if np.isfinite(top) and np.isfinite(bottom) and np.isfinite(left) and np.isfinite(right):
                        t_tl = 1.0 / np.sqrt(top * top + left * left + 1.0)
                        t_tr = 1.0 / np.sqrt(top * top + right * right + 1.0)
                        t_bl = 1.0 / np.sqrt(bottom * bottom + left * left + 1.0)
                        t_br = 1.0 / np.sqrt(bottom * bottom + right * right + 1.0)
                        dr_x[r, c] += sdr_scale * top * (t_tl + t_tr)
                        dr_x[r + 1, c] += sdr_scale * bottom * (t_bl + t_br)
                        dr_y[r, c] += sdr_scale * left * (t_tl + t_bl)
                        dr_y[r, c + 1] += sdr_scale * right * (t_tr + t_br)
                        total += (
                            (top * top + left * left) * t_tl + (top * top + right * right) * t_tr
                            + (bottom * bottom + left * left) * t_bl + (bottom * bottom + right * right) * t_br
                        )  # fmt: skip
            scale_terms[r] = total
    return dq_x, dq_y, dr_x, dr_y, sdr_scale * scale_terms.sum()


@numba.njit(parallel=True, **_JIT)
def edge_block_sums(sigma, d_x, d_y, inverse_pixel, block):
    """Block sums of sigma · dP/dz, where dP/dz of a pixel is the sum over its edges of dP/d(slope)
    times d(slope)/dz = ±1 / pixel (+ at the edge's end, - at its start)."""
    rows, cols = sigma.shape
    out_rows, out_cols = (rows + block - 1) // block, (cols + block - 1) // block
    sums = np.zeros((out_rows, out_cols))
    for br in numba.prange(out_rows):
        for r in range(br * block, min(rows, (br + 1) * block)):
            for c in range(cols):
                w = 0.0
                if c > 0:
                    w += d_x[r, c - 1]
                if c + 1 < cols:
                    w -= d_x[r, c]
                if r > 0:
                    w += d_y[r - 1, c]
                if r + 1 < rows:
                    w -= d_y[r, c]
                sums[br, c // block] += sigma[r, c] * w * inverse_pixel
    return sums


# Feature parameters: steepest-ascent watershed ######################################################


@numba.njit(**_JIT)
def ascent_labels(heights):
    """Label each pixel 1..n with the local maximum (plateau: an 8-connected set of pixels none of
    whose neighbours is higher) that steepest ascent reaches from it; the steepest neighbour is the
    highest, the first in row-major neighbour order on ties. Returns (labels, flat index of the
    last pixel, row-major, of each label's maximum; index 0 unused)."""
    rows, cols = heights.shape
    n = rows * cols
    target = np.empty(n, dtype=np.int64)
    for r in range(rows):
        for c in range(cols):
            best = -np.inf
            chosen = r * cols + c
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    if dr == 0 and dc == 0:
                        continue
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < rows and 0 <= cc < cols and heights[rr, cc] > best:
                        best = heights[rr, cc]
                        if best > heights[r, c]:
                            chosen = rr * cols + cc
            target[r * cols + c] = chosen if best > heights[r, c] else r * cols + c
    labels = np.zeros(n, dtype=np.int64)
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
    # Every other pixel takes the label its ascent ends at (paths compressed as they are walked).
    for start in range(n):
        if labels[start] != 0:
            continue
        length = 0
        p = start
        while labels[p] == 0:
            stack[length] = p
            length += 1
            p = target[p]
        label = labels[p]
        for i in range(length):
            labels[stack[i]] = label
    return labels.reshape(rows, cols), np.array(peaks, dtype=np.int64)


@numba.njit(**_JIT)
def hill_boundaries(labels, heights):
    """Adjacent hill pairs across every 8-connected boundary (right, down, down-right, down-left
    neighbours): (low label, high label, pass height = the lower of the two heights), runs of the
    same pair along a row folded to their largest pass."""
    rows, cols = labels.shape
    capacity = 1024
    low = np.empty(capacity, dtype=np.int64)
    high = np.empty(capacity, dtype=np.int64)
    value = np.empty(capacity)
    size = 0
    for r in range(rows):
        for c in range(cols):
            a = labels[r, c]
            for k in range(4):
                rr, cc = (r, c + 1) if k == 0 else ((r + 1, c) if k == 1 else ((r + 1, c + 1) if k == 2 else (r + 1, c - 1)))
                if rr >= rows or cc < 0 or cc >= cols:
                    continue
                b = labels[rr, cc]
                if a == b:
                    continue
                lo_label, hi_label = (a, b) if a < b else (b, a)
                height = min(heights[r, c], heights[rr, cc])
                if size > 0 and low[size - 1] == lo_label and high[size - 1] == hi_label:
                    value[size - 1] = max(value[size - 1], height)
                    continue
                if size == capacity:
                    capacity *= 2
                    low = np.resize(low, capacity)
                    high = np.resize(high, capacity)
                    value = np.resize(value, capacity)
                low[size], high[size], value[size] = lo_label, hi_label, height
                size += 1
    return low[:size].copy(), high[:size].copy(), value[:size].copy()


# Filters ###########################################################################################


@numba.njit(parallel=True, **_JIT)
def normalized_separable_filter(z, kernel_rows, kernel_cols):
    """Normalized convolution of a map with a small separable kernel (odd lengths, centred):
    (K * (w z)) / (K * w), w = 1 on finite heights and 0 elsewhere and outside; NaN where z is."""
    rows, cols = z.shape
    half_r, half_c = kernel_rows.size // 2, kernel_cols.size // 2
    numerator = np.empty((rows, cols))
    weight = np.empty((rows, cols))
    for r in numba.prange(rows):
        for c in range(cols):
            total = 0.0
            norm = 0.0
            for t in range(kernel_cols.size):
                cc = c + t - half_c
                if 0 <= cc < cols:
                    v = z[r, cc]
                    if np.isfinite(v):
                        total += kernel_cols[t] * v
                        norm += kernel_cols[t]
            numerator[r, c] = total
            weight[r, c] = norm
    out = np.empty((rows, cols))
    for r in numba.prange(rows):
        for c in range(cols):
            if not np.isfinite(z[r, c]):
                out[r, c] = np.nan
                continue
            total = 0.0
            norm = 0.0
            for t in range(kernel_rows.size):
                rr = r + t - half_r
                if 0 <= rr < rows:
                    total += kernel_rows[t] * numerator[rr, c]
                    norm += kernel_rows[t] * weight[rr, c]
            out[r, c] = total / norm
    return out


@numba.njit(parallel=True, **_JIT)
def block_sums_and_counts(z, block, pad):
    """Sums of the finite heights and their counts over block x block pixels, on a grid of blocks
    that starts `pad` blocks before the map and ends `pad` blocks after it (those empty)."""
    rows, cols = z.shape
    out_rows = (rows + block - 1) // block + 2 * pad
    out_cols = (cols + block - 1) // block + 2 * pad
    sums = np.zeros((out_rows, out_cols))
    counts = np.zeros((out_rows, out_cols))
    for br in numba.prange(out_rows - 2 * pad):
        for r in range(br * block, min(rows, (br + 1) * block)):
            for c in range(cols):
                v = z[r, c]
                if np.isfinite(v):
                    sums[br + pad, c // block + pad] += v
                    counts[br + pad, c // block + pad] += 1.0
    return sums, counts


@numba.njit(**_JIT)
def _cubic_weights(t):
    """Keys' cubic convolution (a = -0.5) weights of the four samples around a point t in [0, 1)."""
    a = -0.5
    w0 = ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a
    w1 = ((a + 2) * t - (a + 3)) * t * t + 1
    u = 1 - t
    w2 = ((a + 2) * u - (a + 3)) * u * u + 1
    w3 = 1.0 - w0 - w1 - w2
    return w0, w1, w2, w3


@numba.njit(parallel=True, **_JIT)
def upsample_cubic(coarse, start, step, rows, cols, known):
    """Separable cubic convolution of a coarse grid at the fine pixels: fine pixel i sits at coarse
    coordinate start + i * step along each axis (every fine pixel at least one coarse sample from
    the coarse grid's edges). NaN where `known` is false."""
    coarse_rows, coarse_cols = coarse.shape
    along_cols = np.empty((coarse_rows, cols))
    for c in numba.prange(cols):
        x = start + c * step
        base = int(np.floor(x))
        w0, w1, w2, w3 = _cubic_weights(x - base)
        for r in range(coarse_rows):
            along_cols[r, c] = (
                w0 * coarse[r, base - 1] + w1 * coarse[r, base] + w2 * coarse[r, base + 1] + w3 * coarse[r, base + 2]
            )
    out = np.empty((rows, cols))
    for r in numba.prange(rows):
        y = start + r * step
        base = int(np.floor(y))
        w0, w1, w2, w3 = _cubic_weights(y - base)
        for c in range(cols):
            if known[r, c]:
                out[r, c] = (
                    w0 * along_cols[base - 1, c] + w1 * along_cols[base, c]
                    + w2 * along_cols[base + 1, c] + w3 * along_cols[base + 2, c]
                )  # fmt: skip
            else:
                out[r, c] = np.nan
    return out
