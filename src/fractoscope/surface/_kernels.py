"""Compiled inner loops of the surface analysis (numba): one pass over a height map where numpy
would make several map-sized temporaries, which on a 4096² map cost more than the arithmetic.
Each kernel computes exactly what the numpy definition in its calling module states; rows are
split across threads (prange) and reduced in float64."""

from __future__ import annotations

import numba
import numpy as np

_JIT = {"cache": True, "nogil": True, "fastmath": False}


@numba.njit(parallel=True, **_JIT)
def height_summary(z):
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
                below = (r + 1) // block
                total = sx = nx = sy = ny = cells = 0.0
                for c in range(cols):
                    v = z[r, c]
                    here, right_block = c // block, (c + 1) // block
                    if c + 1 < cols:
                        gx = (z[r, c + 1] - v) * inverse_pixel
                        if np.isfinite(gx):
                            sx += gx * gx
                            nx += 1.0
                            d = gx * inverse_pixel
                            qx[br, right_block] += d * sigma[r, c + 1]
                            qx[br, here] -= d * sigma[r, c]
                    if r + 1 >= rows:
                        continue
                    gy = (z[r + 1, c] - v) * inverse_pixel
                    if np.isfinite(gy):
                        sy += gy * gy
                        ny += 1.0
                        d = gy * inverse_pixel
                        qy[below, here] += d * sigma[r + 1, c]
                        qy[br, here] -= d * sigma[r, c]
                    if c + 1 >= cols:
                        continue
                    top = (z[r, c + 1] - v) * inverse_pixel
                    bottom = (z[r + 1, c + 1] - z[r + 1, c]) * inverse_pixel
                    left = gy
                    right = (z[r + 1, c + 1] - z[r, c + 1]) * inverse_pixel
                    if not (np.isfinite(top) and np.isfinite(bottom) and np.isfinite(left) and np.isfinite(right)):
                        continue
                    cells += 1.0
                    t_tl = 1.0 / np.sqrt(top * top + left * left + 1.0)
                    t_tr = 1.0 / np.sqrt(top * top + right * right + 1.0)
                    t_bl = 1.0 / np.sqrt(bottom * bottom + left * left + 1.0)
                    t_br = 1.0 / np.sqrt(bottom * bottom + right * right + 1.0)
                    d = inverse_pixel * top * (t_tl + t_tr)  # x edge (r, c) -> (r, c + 1)
                    dr[br, right_block] += d * sigma[r, c + 1]
                    dr[br, here] -= d * sigma[r, c]
                    d = inverse_pixel * bottom * (t_bl + t_br)  # x edge (r + 1, c) -> (r + 1, c + 1)
                    dr[below, right_block] += d * sigma[r + 1, c + 1]
                    dr[below, here] -= d * sigma[r + 1, c]
                    d = inverse_pixel * left * (t_tl + t_bl)  # y edge (r, c) -> (r + 1, c)
                    dr[below, here] += d * sigma[r + 1, c]
                    dr[br, here] -= d * sigma[r, c]
                    d = inverse_pixel * right * (t_tr + t_br)  # y edge (r, c + 1) -> (r + 1, c + 1)
                    dr[below, right_block] += d * sigma[r + 1, c + 1]
                    dr[br, right_block] -= d * sigma[r, c + 1]
                    total += (
                        (top * top + left * left) * t_tl + (top * top + right * right) * t_tr
                        + (bottom * bottom + left * left) * t_bl + (bottom * bottom + right * right) * t_br
                    )  # fmt: skip
                partial[r, 0], partial[r, 1], partial[r, 2] = total, sx, nx
                partial[r, 3], partial[r, 4], partial[r, 5] = sy, ny, cells
    sums = partial.sum(axis=0)
    return qx, qy, dr, sums[0], sums[1], sums[2], sums[3], sums[4], sums[5]


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
                    if (dr != 0 or dc != 0) and (inside or (0 <= rr < rows and 0 <= cc < cols)) and heights[rr, cc] > best:
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
                not down or (labels[r + 1, c] == a and (not right or labels[r + 1, c + 1] == a) and (c == 0 or labels[r + 1, c - 1] == a))
            ):
                continue  # inside a hill, as most pixels are
            for k in range(4):
                rr, cc = (r, c + 1) if k == 0 else ((r + 1, c) if k == 1 else ((r + 1, c + 1) if k == 2 else (r + 1, c - 1)))
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


# Filters ###########################################################################################


@numba.njit(parallel=True, **_JIT)
def normalized_separable_filter(z, kernel_rows, kernel_cols):
    """Normalized convolution of a map with a small separable kernel (odd lengths, centred):
    (K * (w z)) / (K * w), w = 1 on finite heights and 0 elsewhere and outside; NaN where z is.
    Bands of rows at a time, their row pass kept in cache for the column pass."""
    rows, cols = z.shape
    half_r, half_c = kernel_rows.size // 2, kernel_cols.size // 2
    band = 32
    out = np.empty((rows, cols))
    for b in numba.prange((rows + band - 1) // band):
        first, last = b * band, min(rows, (b + 1) * band)
        low, high = max(0, first - half_r), min(rows, last + half_r)
        numerator = np.empty((high - low, cols))
        weight = np.empty((high - low, cols))
        for r in range(low, high):
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
                numerator[r - low, c] = total
                weight[r - low, c] = norm
        for r in range(first, last):
            for c in range(cols):
                if not np.isfinite(z[r, c]):
                    out[r, c] = np.nan
                    continue
                total = 0.0
                norm = 0.0
                for t in range(kernel_rows.size):
                    rr = r + t - half_r
                    if 0 <= rr < rows:
                        total += kernel_rows[t] * numerator[rr - low, c]
                        norm += kernel_rows[t] * weight[rr - low, c]
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
def _cubic_taps(start, step, count):
    """For positions start + i * step (i < count): the first of the four samples around each, and
    Keys' cubic convolution weights (a = -0.5) of the four."""
    first = np.empty(count, dtype=np.int64)
    weights = np.empty((count, 4))
    a = -0.5
    for i in range(count):
        x = start + i * step
        base = int(np.floor(x))
        t = x - base
        u = 1.0 - t
        weights[i, 0] = ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a
        weights[i, 1] = ((a + 2) * t - (a + 3)) * t * t + 1
        weights[i, 2] = ((a + 2) * u - (a + 3)) * u * u + 1
        weights[i, 3] = 1.0 - weights[i, 0] - weights[i, 1] - weights[i, 2]
        first[i] = base - 1
    return first, weights


@numba.njit(parallel=True, **_JIT)
def upsample_cubic(coarse, start, step, rows, cols, known):
    """Separable cubic convolution of a coarse grid at the fine pixels: fine pixel i sits at coarse
    coordinate start + i * step along each axis (every fine pixel at least one coarse sample from
    the coarse grid's edges). NaN where `known` is false."""
    coarse_rows = coarse.shape[0]
    first_c, weights_c = _cubic_taps(start, step, cols)
    first_r, weights_r = _cubic_taps(start, step, rows)
    along_cols = np.zeros((coarse_rows, cols))
    for c in numba.prange(cols):
        for t in range(4):
            along_cols[:, c] += weights_c[c, t] * coarse[:, first_c[c] + t]
    out = np.empty((rows, cols))
    for r in numba.prange(rows):
        w0, w1, w2, w3 = weights_r[r, 0], weights_r[r, 1], weights_r[r, 2], weights_r[r, 3]
        a0, a1, a2, a3 = along_cols[first_r[r]], along_cols[first_r[r] + 1], along_cols[first_r[r] + 2], along_cols[first_r[r] + 3]
        for c in range(cols):
            out[r, c] = ((w0 * a0[c] + w1 * a1[c]) + w2 * a2[c]) + w3 * a3[c] if known[r, c] else np.nan
    return out


# Scaling ###########################################################################################


@numba.njit(parallel=True, **_JIT)
def bilinear_profiles(z, origin, across, along, offsets, positions):
    """Bilinear samples of z at origin + across · offset + along · position (row, col vectors) for
    each offset (a profile) and position (a sample): (offsets, positions); NaN off the map or where
    a corner is unknown (scipy.ndimage.map_coordinates, order 1, cval NaN)."""
    rows, cols = z.shape
    out = np.empty((offsets.size, positions.size))
    for i in numba.prange(offsets.size):
        base_r = origin[0] + across[0] * offsets[i]
        base_c = origin[1] + across[1] * offsets[i]
        for j in range(positions.size):
            r = base_r + along[0] * positions[j]
            c = base_c + along[1] * positions[j]
            r0, c0 = int(np.floor(r)), int(np.floor(c))
            if r < 0 or c < 0 or r > rows - 1 or c > cols - 1:
                out[i, j] = np.nan
                continue
            r1, c1 = min(r0 + 1, rows - 1), min(c0 + 1, cols - 1)
            fr, fc = r - r0, c - c0
            out[i, j] = (
                (1 - fr) * ((1 - fc) * z[r0, c0] + fc * z[r0, c1]) + fr * ((1 - fc) * z[r1, c0] + fc * z[r1, c1])
            )
    return out


@numba.njit(parallel=True, **_JIT)
def difference_sums(profiles, lags, order, band_starts, segments):
    """Sums and counts of the squared order-th differences of the profiles at each lag, per block:
    bands of profiles (starting at band_starts) times `segments` stretches along them, those of
    np.array_split (a difference counted in the stretch where it starts). Each profile is summed
    on its own, while it is in cache, then the profiles of a band in order. Returns (bands,
    segments, lags) twice."""
    count, length = profiles.shape
    bands = band_starts.size
    each_sums = np.zeros((count, segments, lags.size))
    each_counts = np.zeros((count, segments, lags.size))
    for p in numba.prange(count):
        for j in range(lags.size):
            lag = lags[j]
            span = order * lag
            starts = length - span
            size, extra = starts // segments, starts % segments
            begin = 0
            for s in range(segments):
                end = begin + size + (1 if s < extra else 0)
                total, n = 0.0, 0.0
                for i in range(begin, end):
                    if order == 1:
                        d = profiles[p, i + lag] - profiles[p, i]
                    else:
                        d = profiles[p, i + span] - 2.0 * profiles[p, i + lag] + profiles[p, i]
                    if np.isfinite(d):
                        total += d * d
                        n += 1.0
                each_sums[p, s, j], each_counts[p, s, j] = total, n
                begin = end
    sums = np.zeros((bands, segments, lags.size))
    counts = np.zeros((bands, segments, lags.size))
    for b in range(bands):
        end = band_starts[b + 1] if b + 1 < bands else count
        for p in range(band_starts[b], end):
            sums[b] += each_sums[p]
            counts[b] += each_counts[p]
    return sums, counts


@numba.njit(**_JIT)
def bin_spectra(power, log_k, index, band, sums, counts, log_k_sums, k_counts):
    """Adds each profile's spectrum, power (profiles, K) at wavenumbers of logarithm log_k (K,), to
    the bins index (K,; outside where not in 0 .. bins - 1) of its band: sums and counts (bands,
    bins); and each wavenumber's log_k and 1 per profile to log_k_sums and k_counts (bins,)."""
    bins = k_counts.size
    for j in range(index.size):
        if 0 <= index[j] < bins:
            log_k_sums[index[j]] += log_k[j] * power.shape[0]
            k_counts[index[j]] += power.shape[0]
    for row in range(power.shape[0]):
        for j in range(index.size):
            if 0 <= index[j] < bins:
                sums[band[row], index[j]] += power[row, j]
                counts[band[row], index[j]] += 1.0


@numba.njit(**_JIT)
def longest_known_runs(profiles):
    """Start and length of each profile's longest run of finite samples (the first of the longest;
    0, 0 for none)."""
    count, length = profiles.shape
    starts = np.zeros(count, dtype=np.int64)
    lengths = np.zeros(count, dtype=np.int64)
    for p in range(count):
        run_start = -1
        for i in range(length + 1):
            finite = i < length and np.isfinite(profiles[p, i])
            if finite and run_start < 0:
                run_start = i
            elif not finite and run_start >= 0:
                if i - run_start > lengths[p]:
                    starts[p], lengths[p] = run_start, i - run_start
                run_start = -1
    return starts, lengths


@numba.njit(parallel=True, **_JIT)
def windowed_differences(z, hann_rows, hann_cols):
    """For the areal PSD: the differences along columns and along rows on the (rows - 1, cols - 1)
    grid, each less its mean over the finite ones, times the Hann windows; 0 where unknown.
    float32, (along columns, along rows)."""
    rows, cols = z.shape[0] - 1, z.shape[1] - 1
    out_x = np.zeros((rows, cols), dtype=np.float32)
    out_y = np.zeros((rows, cols), dtype=np.float32)
    partial = np.zeros((rows, 4))
    for r in numba.prange(rows):
        total_x = count_x = total_y = count_y = 0.0
        for c in range(cols):
            dx = z[r, c + 1] - z[r, c]
            dy = z[r + 1, c] - z[r, c]
            if np.isfinite(dx):
                total_x += dx
                count_x += 1.0
            if np.isfinite(dy):
                total_y += dy
                count_y += 1.0
        partial[r, 0], partial[r, 1], partial[r, 2], partial[r, 3] = total_x, count_x, total_y, count_y
    sums = partial.sum(axis=0)
    mean_x, mean_y = sums[0] / sums[1], sums[2] / sums[3]
    for r in numba.prange(rows):
        for c in range(cols):
            dx = z[r, c + 1] - z[r, c]
            dy = z[r + 1, c] - z[r, c]
            if np.isfinite(dx):
                out_x[r, c] = (dx - mean_x) * hann_rows[r] * hann_cols[c]
            if np.isfinite(dy):
                out_y[r, c] = (dy - mean_y) * hann_rows[r] * hann_cols[c]
    return out_x, out_y


@numba.njit(parallel=True, **_JIT)
def radial_bins(spectrum_x, spectrum_y, cols, scale, pixel_size_um, log_q_min, log_step, bins):
    """Radial log-binning of the areal PSD of the gradient: the power |X|² + |Y|² (float32) of the
    rfft half-planes of the two differences of a (rows, cols) grid, each value divided by the
    differences' transfer 4 (sin² pi fx + sin² pi fy) and times `scale`, columns other than 0 and
    Nyquist counted twice (they stand for two frequencies). Bin k holds q in [10^(log_q_min + k
    log_step), ...). Returns (sums, counts)."""
    rows, half = spectrum_x.shape
    chunks = min(rows, 16)
    sums = np.zeros((chunks, bins))
    counts = np.zeros((chunks, bins))
    s_cols = np.sin(np.pi * (np.arange(half) / cols)) ** 2
    for chunk in numba.prange(chunks):
        for r in range(chunk * rows // chunks, (chunk + 1) * rows // chunks):
            f_r = (r if r < (rows + 1) // 2 else r - rows) / rows
            s_r = np.sin(np.pi * f_r) ** 2
            for c in range(half):
                if r == 0 and c == 0:
                    continue
                f_c = c / cols
                q = np.sqrt(f_r * f_r + f_c * f_c) / pixel_size_um
                k = int(np.floor((np.log10(q) - log_q_min) / log_step))
                if k < 0 or k >= bins:
                    continue
                x, y = spectrum_x[r, c], spectrum_y[r, c]
                power = (x.real * x.real + x.imag * x.imag) + (y.real * y.real + y.imag * y.imag)
                weight = 2.0 if 1 <= c < (cols + 1) // 2 else 1.0
                transfer = 4.0 * (s_r + s_cols[c])
                sums[chunk, k] += weight * power * scale / transfer
                counts[chunk, k] += weight
    return sums.sum(axis=0), counts.sum(axis=0)


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
