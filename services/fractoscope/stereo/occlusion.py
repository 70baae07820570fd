"""Which way up the relief is, from occlusion: geometry alone, whatever the detector.

Parallel projection maps heights z seen at tilts (t1, t2) and -z seen at (-t1, -t2) onto the same
image positions, so the disparities alone cannot tell a relief from its mirror image; nor can the
ordering constraint or the hidden bands beside walls (both readings predict the same bands at the
same places). What tells them apart is the occluding contour of a smooth occluder (a rounded
particle, a rounded step edge, a pit's rounded rim). A view sees the occluder's surface up to
where its rays graze it; just before that contour the surface is seen by both views, but the
view whose contour it is sees it compressed to nothing: along the rows, du2/du1 -> 0 (a square-root
fold of the disparity, dd/du1 -> -1) on the occluder's side of the band that view cannot see.
The occluder is the higher surface, so the side of the band with the fold tells whether heights
grow with the disparity (the tilt step is positive in the arrays' frame) or fall with it.

A sharp edge has no fold: with textures seen in one view only, a raised square with vertical walls
and the square hole the mirror reading gives are both consistent (Julesz's random-dot stereograms),
so sharp steps are left undecided, not guessed.

Per row, each fall of the disparity by more than MIN_FALL_PX (a band the second view cannot see)
is aligned again from the images alone, by dynamic programming over 7-row columns: a monotone map
of the row onto the second view, a hidden band in it (the second view's position frozen), resumed
within 2 px. Two readings are scored, each forbidding the compression of a fold (0.125 < du2/du1 <
_FOLD_M) on one side of the band, over `_FOLD_COLUMNS` columns that end `_GAP_COLUMNS` columns
before it (the last few pixels are left free on both sides: there the band's own texture, which
continues its owner's, and the renderer's or the microscope's edge effects, resemble a fold).
The reading that forbids the fold where there is one pays for it; the difference of the two costs is
the row's evidence. Rows are joined into walls along the columns, and a wall votes where its summed
evidence is clear, the disparity on the fold's side slopes towards the band further out (a smooth
occluder's flank) and the other side is level (the ground the band belongs to), as a sharp step's
flat terraces and a crowd of occluders are not (`_MIN_FLANK_SLOPE`). The second view is
treated as the reference the same way (the occluders' other sides, where the first view's contour
lies). A sign test over the walls decides, as relief_sign's rules do, so that a few walls cannot
outvote the rest; rows of one wall are never counted as independent.

The alignment never uses the matcher's disparities near a wall, only `_ANCHOR_PX` away from the
band on both sides, so the rules a matcher applies beside occlusions (`visibility`, which assume
one sign of the tilt step) do not shape the verdict; and the whole procedure is the same on the
pair with its columns reversed, which swaps the two readings exactly.

Measurements, limits and the renderer's part in them: docs/matching-notes.md.

Convention: disparity d at reference pixel (row, col) means it matches (row, col + d) of the second
view resampled onto the reference's grid; the tilt axis runs along the columns.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from fractoscope.stereo import relief_sign
from fractoscope.stereo.matching import local_contrast
from fractoscope.stereo.relief_sign import ReliefSign

# A disparity that falls by more than this across a hole hides a band worth looking at, px.
MIN_FALL_PX = 3.0
# Rows looked at: every third (the columns span 7 rows; neighbours would repeat them).
_ROW_STEP = 4
_HALF_ROWS = 3
# The matched disparity is trusted this far from the hole, px; holes wider than _MAX_HOLE_PX
# (the matcher lost a whole face, not a band) are left alone.
_ANCHOR_PX = 20
_MAX_HOLE_PX = 80
_LEVEL_PX = 12
# The alignment's grid: second-view positions every 1/8 px, du2/du1 from 0 to 1.5 in 1/8 steps.
_GRID_PX = 0.125
_MAX_STEP = 12
_STATIONARY_STEP = 1
# Where a fold is forbidden: du2/du1 under _FOLD_M (but not stationary) on _FOLD_COLUMNS columns
# ending _GAP_COLUMNS columns before the band.
_FOLD_M = 0.9
_FOLD_COLUMNS = 12
_GAP_COLUMNS = 5
# How much a hidden column costs, in multiples of the pair's median cost of a matched column.
_HIDDEN_COST = 4.0
_CHANGE_COST = 0.6
# The constrained alignments are looked for among positions the free ones reach within this cost
# (in median column costs) of their best.
_CORRIDOR_COST = 40.0
_START_SLACK_PX = 2.0
_RESUME_PX = 2.0
# A wall of at least _MIN_WALL_ROWS rows (at most _MAX_WALL_ROWS of them looked at) votes where
# its summed evidence passes _MIN_WALL_EVIDENCE (in median column costs), the disparity on the
# fold's side falls along the columns by more than 2 _MIN_FLANK_SLOPE px/px between _FLANK_PX[0]
# and _FLANK_PX[1] px from the hole (a smooth occluder's flank: d falls towards its contour before
# the band, away from it after), and the other side is level within _MIN_FLANK_SLOPE (the ground
# the band belongs to). Sharp steps have no such flank; where the other side slopes too (a second
# occluder, a rough fracture) the secant law's bright steep faces, seen in both views, align
# with each other and mimic a fold on either side.
_MIN_WALL_ROWS = 4
_MAX_WALL_ROWS = 16
_MIN_WALL_EVIDENCE = 25.0
_MIN_FLANK_SLOPE = 0.03
_FLANK_PX = (12, 36)
# A hole with another wall where its flanks are measured is left alone: the disparity changes
# there by more than this, px/px (`_alone`).
_MAX_SIDE_SLOPE = 0.4
# Each view's contours must give at least this many walls for a decision (`verdict`).
_MIN_VIEW_VOTES = 3
# Rows of one wall: hole starts at most this far apart between rows looked at, px.
_WALL_LINK_PX = 6


def relief_sign_from_occlusion(
    reference: np.ndarray, second_on_first: np.ndarray, disparity_px: np.ndarray, *, tilt_step_sign: float
) -> ReliefSign:
    """Whether the relief the pair shows is the one the tilts as given say, from the occluding
    contours beside the bands the views cannot see.

    reference, second_on_first: (rows, cols) grey images, the second resampled onto the
    reference's grid (rectified: the tilt axis along the columns); disparity_px: (rows, cols)
    float, NaN where unknown, as matched between them; tilt_step_sign: the sign of the tilt step
    as given (second view's tilt minus the reference's) in this frame (heights as given grow with
    the disparity where it is positive). Returns a ReliefSign with cue "occlusion" (blocks: the
    walls that voted) or "none" where no wall could vote."""
    if reference.shape != second_on_first.shape or reference.shape != disparity_px.shape or reference.ndim != 2:
        raise ValueError("reference, second_on_first and disparity_px must be 2D of one shape")
    return verdict(wall_votes(reference, second_on_first, disparity_px), tilt_step_sign=tilt_step_sign)


def verdict(votes: tuple[np.ndarray, np.ndarray], *, tilt_step_sign: float) -> ReliefSign:
    """The sign test over `wall_votes` (+1: heights grow with the disparity) against the tilt
    step as given (its sign, in the frame the votes were taken in), by relief_sign's rules; and
    the contours of each view must agree on their own (at least _MIN_VIEW_VOTES walls each, the
    majority of each MIN_STRENGTH lopsided the same way): a photometric effect of one view's
    incidence (its grazing rays darken or brighten what lies near its contours) fools only that
    view's walls."""
    if not np.isfinite(tilt_step_sign) or tilt_step_sign == 0:
        return relief_sign.undetermined("the tilt step is zero or not known")
    agreeing = [int(np.sum(view * np.sign(tilt_step_sign) > 0)) for view in votes]
    total, agreeing_total = sum(len(view) for view in votes), sum(agreeing)
    told = relief_sign.sign_test(
        agreeing_total,
        total - agreeing_total,
        cue="occlusion",
        too_few=f"too few walls with a rounded occluding edge ({total} of {relief_sign.MIN_BLOCKS} needed)",
        ambiguous=f"the occlusions are ambiguous ({agreeing_total} of {total} walls agree with the tilts)",
    )
    balances = [(2 * agree - len(view)) / max(len(view), 1) for agree, view in zip(agreeing, votes)]
    consistent = all(len(view) >= _MIN_VIEW_VOTES for view in votes) and (
        all(balance >= relief_sign.MIN_STRENGTH for balance in balances)
        or all(balance <= -relief_sign.MIN_STRENGTH for balance in balances)
    )
    if told.decided and not consistent:
        counts = " and ".join(f"{agree} of {len(view)}" for agree, view in zip(agreeing, votes))
        reason = f"the two views' occluding contours do not agree ({counts} walls agree with the tilts)"
        return dataclasses.replace(told, decided=False, reason=reason)
    return told


def wall_votes(
    reference: np.ndarray, second_on_first: np.ndarray, disparity_px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One vote per wall with a fold beside its band (int8): +1 where the occluder has the larger
    disparity (heights grow with it: a positive tilt step in this frame), -1 where the smaller;
    the walls at the second view's contours (the reference's hidden bands), then those at the
    reference's (with the second view as the reference: its disparities are the first's inverted)."""
    first = local_contrast(np.asarray(reference, np.float32)).astype(np.float64)
    second = local_contrast(np.asarray(second_on_first, np.float32)).astype(np.float64)
    disparity = np.asarray(disparity_px, np.float64)
    direct = _side_votes(first, second, disparity)
    # With the second view as the reference the step is the other way round.
    swapped = -_side_votes(second, first, inverted_disparity(disparity))
    return direct.astype(np.int8), swapped.astype(np.int8)


def _side_votes(first: np.ndarray, second: np.ndarray, disparity_px: np.ndarray) -> np.ndarray:
    """Votes of the walls at falls of `disparity_px` (first view the reference): +1 where the fold
    is before the band (the occluder has the larger disparity), -1 after it."""
    rows, starts, ends = fall_candidates(disparity_px)
    walls = _walls(rows, starts)
    sampled = _sampled_rows(walls)
    rows, starts, ends, walls = rows[sampled], starts[sampled], ends[sampled], walls[sampled]
    scale = _matched_column_cost(first, second, disparity_px)
    if not len(rows) or not scale > 0:
        return np.zeros(0)

    def evidence_at(candidate):
        return _fold_evidence(first, second, disparity_px, *candidate, scale)

    with ThreadPoolExecutor(max_workers=2) as pool:  # the alignments are compiled and release the GIL
        evidence = np.array(list(pool.map(evidence_at, zip(rows, starts, ends))))
    flanks = _flank_slopes(disparity_px, rows, starts, ends)
    votes = []
    for wall in np.unique(walls):
        members = (walls == wall) & np.isfinite(evidence)
        if members.sum() < _MIN_WALL_ROWS:
            continue
        total = float(evidence[members].sum()) / scale
        before, after = (_median_or_zero(flanks[members, side]) for side in (0, 1))
        if total > _MIN_WALL_EVIDENCE and before < -2 * _MIN_FLANK_SLOPE and abs(after) < _MIN_FLANK_SLOPE:
            votes.append(1)
        elif total < -_MIN_WALL_EVIDENCE and after < -2 * _MIN_FLANK_SLOPE and abs(before) < _MIN_FLANK_SLOPE:
            votes.append(-1)
    return np.asarray(votes)


def fall_candidates(disparity_px: np.ndarray):
    """The holes of `disparity_px` across which it falls by more than MIN_FALL_PX (medians of
    _LEVEL_PX px each side), on every _ROW_STEP-th row, with _ANCHOR_PX px of known disparity
    around: (rows, starts, ends) int arrays, the hole being columns start:end."""
    found = []
    known = np.isfinite(disparity_px)
    cols = disparity_px.shape[1]
    for row in range(_HALF_ROWS, disparity_px.shape[0] - _HALF_ROWS, _ROW_STEP):
        valid = known[row]
        starts = np.flatnonzero(valid[:-1] & ~valid[1:]) + 1
        ends = np.flatnonzero(~valid[:-1] & valid[1:]) + 1
        for start in starts:
            later = ends[ends > start]
            if not len(later):
                break
            end = int(later[0])
            if end - start > _MAX_HOLE_PX or start < _ANCHOR_PX or end - 1 + _ANCHOR_PX >= cols:
                continue
            if not (valid[start - _ANCHOR_PX] and valid[end - 1 + _ANCHOR_PX]):
                continue
            before = disparity_px[row, start - _LEVEL_PX : start]
            after = disparity_px[row, end : end + _LEVEL_PX]
            if np.isfinite(before).sum() < _LEVEL_PX // 2 or np.isfinite(after).sum() < _LEVEL_PX // 2:
                continue
            if np.nanmedian(before) - np.nanmedian(after) > MIN_FALL_PX and _alone(disparity_px[row], start, end):
                found.append((row, start, end))
    found = np.asarray(found, np.int64).reshape(-1, 3)
    return found[:, 0], found[:, 1], found[:, 2]


def _alone(disparity_px: np.ndarray, start: int, end: int) -> bool:
    """Whether the row `disparity_px` (cols) has no other wall where the hole start:end's flanks
    are measured (_FLANK_PX before and after it): nowhere there does it change by more than
    _MAX_SIDE_SLOPE px/px over 4 px (a neighbouring step or occluder would lend the hole its
    flank)."""
    near, far = _FLANK_PX
    for side in (disparity_px[max(start - far, 0) : max(start - near, 0)], disparity_px[end + near : end + far]):
        change = np.abs(side[4:] - side[:-4])
        if np.isfinite(side).sum() < (far - near) // 2 or np.nanmax(change, initial=0.0) > 4 * _MAX_SIDE_SLOPE:
            return False
    return True


def _fold_evidence(first, second, disparity_px, row, start, end, scale) -> float:
    """How much more the row's alignment costs with a fold forbidden before the band than after
    it (positive: the fold is before it), in the images' squared units; NaN where no alignment
    fits."""
    left, right = start - _ANCHOR_PX, end - 1 + _ANCHOR_PX
    from_px = left + disparity_px[row, left] - _START_SLACK_PX
    to_px = right + disparity_px[row, right] + _START_SLACK_PX
    positions = int(np.ceil((to_px - from_px) / _GRID_PX)) + 1
    if positions < 8:
        return float("nan")
    cost = _column_costs(first, second, row, left, right, from_px, positions, _GRID_PX, _HALF_ROWS)
    steps = (_MAX_STEP, _STATIONARY_STEP, int(round(2 * _START_SLACK_PX / _GRID_PX)), int(round(_RESUME_PX / _GRID_PX)))
    settings = (steps, (_HIDDEN_COST * scale, _CHANGE_COST * scale))
    low, high = _corridor(cost, settings, _CORRIDOR_COST * scale)
    fold_step = int(round(_FOLD_M / _GRID_PX))
    none = np.zeros((0, 0))
    no_fold_before = _aligned_cost(cost, settings, (fold_step, _FOLD_COLUMNS, _GAP_COLUMNS, 0), low, high, none)
    no_fold_after = _aligned_cost(cost, settings, (fold_step, 0, _GAP_COLUMNS, _FOLD_COLUMNS), low, high, none)
    return float(no_fold_before - no_fold_after) if np.isfinite(no_fold_before + no_fold_after) else float("nan")


def _corridor(cost: np.ndarray, settings, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Per column, the lowest and highest position (int64) of the alignments without constraints
    whose cost is within `margin` of the best, widened by _RESUME_PX: the constrained alignments
    are looked for there only. The same from either end, so that it has no preferred direction."""
    columns, positions = cost.shape
    everywhere = (np.zeros(columns, np.int64), np.full(columns, positions - 1, np.int64))
    free = (0, 0, 0, 0)
    reached = np.full((2, columns, positions), np.inf)
    for side, table in enumerate((cost, np.ascontiguousarray(cost[::-1, ::-1]))):
        reached[side, 0, : settings[0][2] + 1] = table[0, : settings[0][2] + 1]
        _aligned_cost(table, settings, free, *everywhere, reached[side])
    through = reached[0] + reached[1, ::-1, ::-1] - cost
    near = through <= through.min(axis=1, keepdims=True) + margin
    widen = int(round(_RESUME_PX / _GRID_PX))
    low = np.clip(np.argmax(near, axis=1) - widen, 0, positions - 1)
    high = np.clip(positions - 1 - np.argmax(near[:, ::-1], axis=1) + widen, 0, positions - 1)
    return low.astype(np.int64), high.astype(np.int64)


def _flank_slopes(disparity_px: np.ndarray, rows, starts, ends) -> np.ndarray:
    """(candidates, 2): the disparity's slope (px/px along the columns) between _FLANK_PX[0] and
    _FLANK_PX[1] px before each hole and after it, NaN where less than half of it is known."""
    near, far = _FLANK_PX
    slopes = np.full((len(rows), 2), np.nan)
    for index, (row, start, end) in enumerate(zip(rows, starts, ends)):
        for side, columns in enumerate((np.arange(start - far, start - near), np.arange(end + near, end + far))):
            columns = columns[(columns >= 0) & (columns < disparity_px.shape[1])]
            values = disparity_px[row, columns]
            known = np.isfinite(values)
            if known.sum() >= (far - near) // 2:
                slopes[index, side] = np.polyfit(columns[known], values[known], 1)[0]
    return slopes


def _walls(rows: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Labels joining candidates into walls: a candidate continues the wall whose last row is at
    most two steps above it and whose hole started within _WALL_LINK_PX of its own."""
    labels = np.full(len(rows), -1)
    ends: list[tuple[int, int]] = []  # per wall: its last (row, start)
    for index in np.lexsort((starts, rows)):
        near = [
            (abs(starts[index] - start), wall)
            for wall, (row, start) in enumerate(ends)
            if 0 < rows[index] - row <= 2 * _ROW_STEP and abs(starts[index] - start) <= _WALL_LINK_PX
        ]
        wall = min(near)[1] if near else len(ends)
        if wall == len(ends):
            ends.append((0, 0))
        ends[wall] = (int(rows[index]), int(starts[index]))
        labels[index] = wall
    return labels


def _median_or_zero(values: np.ndarray) -> float:
    """The median of the finite `values`, 0 where there are none."""
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if len(finite) else 0.0


def _sampled_rows(walls: np.ndarray) -> np.ndarray:
    """Indices of at most _MAX_WALL_ROWS candidates of each wall of at least _MIN_WALL_ROWS,
    evenly spread along it (a long straight step would otherwise cost as much as many walls)."""
    kept = []
    for wall in np.unique(walls):
        members = np.flatnonzero(walls == wall)
        if len(members) >= _MIN_WALL_ROWS:
            kept.extend(
                members[np.linspace(0, len(members) - 1, min(len(members), _MAX_WALL_ROWS)).round().astype(int)]
            )
    return np.unique(np.asarray(kept, np.int64))


def inverted_disparity(disparity_px: np.ndarray) -> np.ndarray:
    """The second view's disparities to the reference on the same grid ((rows, cols), NaN where
    unknown): along each row, u = col + d inverted where it grows, within runs of known values."""
    rows, cols = disparity_px.shape
    inverted = np.full((rows, cols), np.nan)
    grid = np.arange(cols, dtype=np.float64)
    for row in range(rows):
        known = np.isfinite(disparity_px[row])
        edges = np.flatnonzero(np.diff(np.concatenate([[0], known.astype(np.int8), [0]])))
        for start, stop in zip(edges[::2], edges[1::2]):
            source = grid[start:stop]
            target = source + disparity_px[row, start:stop]
            if stop - start < 2 or np.any(np.diff(target) <= 0):
                continue
            inside = (grid >= target[0]) & (grid <= target[-1])
            inverted[row, inside] = np.interp(grid[inside], target, source) - grid[inside]
    return inverted


def _matched_column_cost(first: np.ndarray, second: np.ndarray, disparity_px: np.ndarray) -> float:
    """The median cost of a matched column (mean squared difference over its 2 _HALF_ROWS + 1
    rows) at the given disparities, on a sample of known pixels: the unit of the evidence."""
    known_rows, known_cols = np.nonzero(np.isfinite(disparity_px))
    inner = (known_rows >= _HALF_ROWS) & (known_rows < disparity_px.shape[0] - _HALF_ROWS)
    known_rows, known_cols = known_rows[inner], known_cols[inner]
    if not len(known_rows):
        return float("nan")
    pick = np.linspace(0, len(known_rows) - 1, min(len(known_rows), 4000)).astype(np.int64)
    costs = _sampled_costs(first, second, disparity_px, known_rows[pick], known_cols[pick], _HALF_ROWS)
    return float(np.nanmedian(costs))


@numba.njit(cache=True, nogil=True)
def _sample(image, row, position):  # pragma: no cover - compiled
    last = image.shape[1] - 1
    position = min(max(position, 0.0), float(last))
    low = min(int(position), last - 1)
    fraction = position - low
    return image[row, low] * (1.0 - fraction) + image[row, low + 1] * fraction


@numba.njit(cache=True, nogil=True)
def _sampled_costs(first, second, disparity_px, rows, cols, half_rows):  # pragma: no cover - compiled
    costs = np.full(len(rows), np.nan)
    for index in range(len(rows)):
        total, count = 0.0, 0
        for offset in range(-half_rows, half_rows + 1):
            row = rows[index] + offset
            shift = disparity_px[row, cols[index]]
            if np.isfinite(shift):
                difference = first[row, cols[index]] - _sample(second, row, cols[index] + shift)
                total += difference * difference
                count += 1
        if count == 2 * half_rows + 1:
            costs[index] = total / count
    return costs


@numba.njit(cache=True, nogil=True)
def _column_costs(first, second, row, left, right, from_px, positions, grid_px, half_rows):  # pragma: no cover
    """(columns, positions): mean squared difference of each first-view column (rows row +-
    half_rows) and the second view at each grid position."""
    cost = np.empty((right - left + 1, positions))
    last_row = first.shape[0] - 1
    for column in range(right - left + 1):
        for position in range(positions):
            total = 0.0
            for offset in range(-half_rows, half_rows + 1):
                source = min(max(row + offset, 0), last_row)
                difference = first[source, left + column] - _sample(second, source, from_px + position * grid_px)
                total += difference * difference
            cost[column, position] = total / (2 * half_rows + 1)
    return cost


@numba.njit(cache=True, nogil=True)
def _eased(state, change_cost, eased, low, high):  # pragma: no cover - compiled
    """Each state's best cost over its step and the steps one either side (at change_cost), at
    positions low..high."""
    count, _, steps = state.shape
    for index in range(count):
        for position in range(low, high + 1):
            for step in range(steps):
                best = state[index, position, step]
                if step > 0:
                    best = min(best, state[index, position, step - 1] + change_cost)
                if step + 1 < steps:
                    best = min(best, state[index, position, step + 1] + change_cost)
                eased[index, position, step] = best


@numba.njit(cache=True, nogil=True)
def _hidden_moves(state, hidden, costs, resume, window, upcoming, frozen):  # pragma: no cover - compiled
    """The hidden run's next costs (entered from the state before it, or continued) into
    `upcoming`, and in `frozen` the best hidden cost within `resume` of each position (to resume
    matching from); `costs` (hidden, change), `window` (the last column's and this one's
    position bounds)."""
    last_low, last_high, low, high = window
    steps = state.shape[2]
    for position in range(max(low, last_low), min(high, last_high) + 1):
        best = state[hidden, position, 0]
        for step in range(steps):
            best = min(best, state[hidden - 1, position, step])
        upcoming[hidden, position, 0] = best + costs[0]
    for position in range(last_low, last_high + 1):
        best = np.inf
        for other in range(max(position - resume, last_low), min(position + resume, last_high) + 1):
            best = min(best, state[hidden, other, 0])
        frozen[position] = best + costs[1]


@numba.njit(cache=True, nogil=True)
def _aligned_cost(cost, settings, fold, low, high, reached):  # pragma: no cover - compiled
    """The least cost of a monotone map of the columns onto the positions (steps 0..max_step per
    column, changing by at most one per column at change_cost each) that starts and ends within
    `slack` positions of the first and last, with one hidden run (hidden_cost per column, the
    position frozen, resumed within `resume`) and, on the `before` columns ending `gap` columns
    before it and the `after` columns starting `gap` after it, no step between `stationary` and
    `fold_step` (no fold). settings: (max_step, stationary, slack, resume), (hidden_cost,
    change_cost); fold: (fold_step, before, gap, after). Only positions low[c]..high[c] of
    column c are looked at; `reached` (columns, positions), if of that shape, gets the least
    cost of reaching each."""
    (max_step, stationary, slack, resume), costs = settings
    fold_step, before, gap, after = fold
    columns, positions = cost.shape
    hidden = before + gap + 1  # states: 0 free, the columns before the band, hidden, after it, free
    count = hidden + gap + after + 2
    steps = max_step + 1
    state = np.full((count, positions, steps), np.inf)
    upcoming = np.full((count, positions, steps), np.inf)
    eased = np.full((count, positions, steps), np.inf)
    frozen = np.full(positions, np.inf)
    for position in range(low[0], min(slack, high[0]) + 1):
        state[0, position, :] = cost[0, position]
    keep = reached.shape[0] == columns
    for column in range(1, columns):
        last_low, last_high, new_low, new_high = low[column - 1], high[column - 1], low[column], high[column]
        _eased(state, costs[1], eased, last_low, last_high)
        clear_low, clear_high = low[max(column - 2, 0)], high[max(column - 2, 0)]
        upcoming[:, min(clear_low, new_low) : max(clear_high, new_high) + 1, :] = np.inf
        _hidden_moves(state, hidden, costs, resume, (last_low, last_high, new_low, new_high), upcoming, frozen)
        for index in range(count):
            if index == hidden:
                continue
            constrained = 1 <= index <= before or hidden + gap < index < count - 1
            loops = index == 0 or index == count - 1
            for position in range(new_low, new_high + 1):
                for step in range(max(position - last_high, 0), min(steps, position - last_low + 1)):
                    if constrained and stationary < step < fold_step:
                        continue
                    previous = position - step
                    best = np.inf
                    if index == hidden + 1:
                        best = frozen[previous]
                    elif index > 0:
                        best = eased[index - 1, previous, step]
                    if loops:
                        best = min(best, eased[index, previous, step])
                    upcoming[index, position, step] = best + cost[column, position]
        state, upcoming = upcoming, state
        if keep:
            for position in range(new_low, new_high + 1):
                reached[column, position] = state[:, position, :].min()
    best = np.inf
    for position in range(max(positions - slack - 1, low[columns - 1]), high[columns - 1] + 1):
        best = min(best, state[count - 1, position].min())
    return best
