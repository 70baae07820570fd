"""The relief's sign of a matched series: the cues' verdict (`relief_sign`), the mode's choice,
and the report's fields and sentence, one wording for every route (CLI, HTTP, gRPC, report)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from fractoscope.sem.instruments import DetectorPlace
from fractoscope.stereo import lighting, occlusion
from fractoscope.stereo.relief_sign import ReliefSign, ReliefSignMode, combined, undetermined

# Where an azimuth as displayed points, by quadrant centred on 0, 90, 180 and 270°.
_SIDES = ("right", "top", "left", "bottom")


@dataclass(frozen=True)
class Orientation:
    """The sign chosen (`inverted`: heights and tilts negated), the images' verdict, and the
    report's relief_sign fields (MatchingReport) with the warnings to add."""

    inverted: bool
    verdict: ReliefSign
    fields: dict
    warnings: list[str]


def oriented(
    reference: np.ndarray,
    matched: Sequence[tuple[np.ndarray, np.ndarray]],
    z_px: np.ndarray,
    tilts_deg: Sequence[float],
    *,
    mode: ReliefSignMode,
    detector: DetectorPlace,
    tilt_axis_deg: float,
) -> Orientation:
    """The relief's sign for heights `z_px` (rows, cols, px, as the tilts given say) of the
    `reference` view (rows, cols, rectified) and the others, each `matched` as (the view resampled
    onto the reference's grid without parallax, the matcher's disparity to it), at `tilts_deg`:
    occlusion's verdict (AUTO mode, on the view of the largest tilt step: the views see the same
    walls), the lighting's where the `detector`'s place is known."""
    views = [reference, *(_through_disparity(view, disparity) for view, disparity in matched)]
    lit = lighting.block_lighting(views, tilts_deg, z_px)
    if detector.known:
        by_lighting = lighting.relief_sign_from_lighting(lit, detector_from_tilt_axis_deg=detector.from_tilt_axis_deg)
    else:
        by_lighting = undetermined(f"the detector's place is {detector.describe()}, so the lighting cannot tell")
    by_occlusion = undetermined("occlusion is judged in auto mode only")
    if mode is ReliefSignMode.AUTO:
        widest = int(np.argmax([abs(tilt - tilts_deg[0]) for tilt in tilts_deg[1:]]))
        step_sign = float(np.sign(tilts_deg[widest + 1] - tilts_deg[0]))
        by_occlusion = occlusion.relief_sign_from_occlusion(reference, *matched[widest], tilt_step_sign=step_sign)
    verdict = combined(by_occlusion, by_lighting)
    inverted = mode is ReliefSignMode.INVERTED or (mode is ReliefSignMode.AUTO and verdict.decided and verdict.inverted)
    direction = lit.significant_direction()
    if direction is not None and inverted:
        direction = ((direction[0] + 360.0) % 360.0 - 180.0, direction[1])  # the lighting of the heights returned
    sentence = verdict_sentence(verdict, inverted=inverted, mode=mode, detector=detector)
    evidence = lighting_evidence(direction, detector, tilt_axis_deg)
    # Undecided is the usual case without a known detector: it is the sentence, not a warning.
    warned = (mode is ReliefSignMode.AUTO and inverted) or (
        mode is not ReliefSignMode.AUTO and verdict.decided and verdict.inverted != inverted
    )
    warnings = [sentence] if warned else []
    fields = {
        "relief_sign": "inverted" if inverted else "nominal",
        "relief_sign_cue": verdict.cue,
        "relief_sign_strength": verdict.strength,
        "relief_sign_confidence": verdict.confidence,
        "relief_sign_decided": verdict.decided,
        "relief_sign_sentence": sentence,
        "relief_sign_evidence": evidence,
        "detector_source": detector.source,
        "detector_from_tilt_axis_deg_used": detector.from_tilt_axis_deg,
        "instrument_profile": detector.profile,
        "lighting_from_tilt_axis_deg": direction[0] if direction else float("nan"),
        "lighting_sigma_deg": direction[1] if direction else float("nan"),
    }
    return Orientation(inverted, verdict, fields, warnings + ([detector.note] if detector.note else []))


def _through_disparity(view: np.ndarray, disparity_px: np.ndarray) -> np.ndarray:
    """`view` (rows, cols, on the reference's grid without parallax) sampled where each reference
    pixel's match lies, (rows, cols) float32, NaN where the disparity is unknown."""
    rows, cols = np.indices(view.shape, dtype=np.float32)
    known = np.isfinite(disparity_px)
    map_cols = cols + np.where(known, disparity_px, 0).astype(np.float32)
    sampled = cv2.remap(view.astype(np.float32), map_cols, rows, cv2.INTER_LINEAR, borderValue=float("nan"))
    return np.where(known, sampled, np.nan).astype(np.float32)


def verdict_sentence(verdict: ReliefSign, *, inverted: bool, mode: ReliefSignMode, detector: DetectorPlace) -> str:
    """The verdict in one sentence, naming its cue and premise."""
    if mode is not ReliefSignMode.AUTO:
        chosen = "mirrored" if inverted else "as the tilts given say"
        sentence = f"The heights are {chosen} (relief_sign {mode.value})"
        if verdict.decided and verdict.inverted != inverted:
            return f"{sentence}, but the images show the relief the other way up ({_cue_text(verdict, detector)})."
        return sentence + "."
    if not verdict.decided:
        return (
            f"The images cannot tell which way up the relief is ({verdict.reason}), so the heights follow the tilts "
            "as given."
        )
    if inverted:
        return (
            f"The relief is inverted under the tilts given ({_cue_text(verdict, detector)}), so the heights use the "
            "tilts with their signs reversed: check the stage's tilt sign, the image order and the tilt axis, or set "
            "relief_sign to nominal to keep the tilts as given."
        )
    return f"The relief is as the tilts given say ({_cue_text(verdict, detector)})."


def _cue_text(verdict: ReliefSign, detector: DetectorPlace) -> str:
    share = verdict.agreeing_share if not verdict.inverted else 1.0 - verdict.agreeing_share
    count = round(share * verdict.blocks)
    if verdict.cue == "occlusion":
        return (
            f"occlusion, from geometry alone: {count} of {verdict.blocks} walls hide their band as this way up requires"
        )
    return (
        f"lighting of a detector at {detector.from_tilt_axis_deg:g}° from the tilt axis, {detector.describe()}: "
        f"{count} of {verdict.blocks} image blocks agree"
    )


def lighting_evidence(direction: tuple[float, float] | None, detector: DetectorPlace, tilt_axis_deg: float) -> str:
    """Where the lighting of the heights returned comes from, as evidence where the detector's
    place is not known ("" where it is known, or where the images show no lighting from a side)."""
    if direction is None or detector.known:
        return ""
    azimuth, sigma = direction
    side = _SIDES[int(((azimuth + tilt_axis_deg) % 360.0 + 45.0) // 90.0) % 4]
    return (
        f"The lighting reads as from {azimuth:.0f} ± {sigma:.0f}° from the tilt axis (the image's {side}) if the "
        "relief is as returned; where the detector really lies (given, or an instrument profile) would let it decide."
    )
