"""Compiled inner loops of the ISO filters and the scaling analysis (numba): separable filters,
block sums, cubic upsampling, profiles, structure functions and spectra, in one pass where numpy
would make several map-sized temporaries. Each kernel computes exactly what the numpy definition
in its calling module states; rows are split across threads (prange) and reduced in float64."""

from __future__ import annotations

import numba
import numpy as np

from fractoscope.surface._kernels import JIT_OPTIONS as _JIT

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
        a0, a1, a2, a3 = (
            along_cols[first_r[r]],
            along_cols[first_r[r] + 1],
            along_cols[first_r[r] + 2],
            along_cols[first_r[r] + 3],
        )
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
            out[i, j] = (1 - fr) * ((1 - fc) * z[r0, c0] + fc * z[r0, c1]) + fr * (
                (1 - fc) * z[r1, c0] + fc * z[r1, c1]
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
