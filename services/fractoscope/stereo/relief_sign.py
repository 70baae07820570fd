"""Which way up the relief is, from the images themselves, and the verdict in words.

Parallel projection cannot tell a relief from its mirror image: heights z seen at tilts
(t1, t2) give the same parallax as heights -z seen at (-t1, -t2), and a stage's tilt sign, an
image order or a tilt axis given 180° off all make that swap. Nor can the secondary-electron
yield's change with the tilt: it depends on the incidence angle |slope angle - tilt| only, which
the swap leaves as it is. Two cues break the symmetry:

- Occlusion (`occlusion`), from geometry alone: the band a wall hides from the other view
  belongs to the lower side. Any detector, in-lens ones included.
- The side detector's lighting (`lighting`): facets facing the detector are brighter. It tells
  the sign only against the detector's place, which the images cannot give: it counts where that
  place is known (given, from an instrument profile), and is otherwise reported as evidence.

Where no cue is decisive the tilts as given are kept, and the verdict says so in one sentence.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from scipy.stats import binomtest

# The evidence decides when chance would give so lopsided a vote with less than this probability.
DECISIVE_P_VALUE = 1e-3
# Nor does a vote less lopsided than this (|agreeing - disagreeing| / all: 90 % of the votes on
# one side). The blocks of a surface whose slopes lie in few large facets (cleavage) are not
# independent, and their sign test alone is overconfident: wrong verdicts there reached 0.77,
# right ones on self-affine and dimpled surfaces 0.85 or more (docs/matching-notes.md).
MIN_STRENGTH = 0.8
# Fewer votes than this decide nothing, whatever their balance.
MIN_BLOCKS = 8


class ReliefSignMode(str, Enum):
    """How the sign of the heights is chosen: from the images where they tell it (AUTO), or as
    the tilts as given say (NOMINAL), or the mirror image of that (INVERTED)."""

    AUTO = "auto"
    NOMINAL = "nominal"
    INVERTED = "inverted"


@dataclass(frozen=True)
class ReliefSign:
    """One cue's verdict on the relief's sign under the tilts as given.

    inverted: the images show the mirrored relief (meaningful where `decided`).
    decided: the evidence is decisive (p_value under DECISIVE_P_VALUE from MIN_BLOCKS or more
        votes, |strength| at least MIN_STRENGTH).
    cue: "occlusion", "lighting", or "none" where no cue could be used (`reason`).
    strength: the votes' balance, (agreeing - disagreeing) / all, -1 to 1 (1: every vote agrees
        with the tilts as given).
    blocks: the number of votes (image blocks for the lighting, walls for occlusion).
    p_value: the chance of so lopsided a vote if the votes told nothing (two-sided sign test).
    reason: why nothing was decided, in one sentence ("" when decided).
    """

    inverted: bool
    decided: bool
    cue: str
    strength: float
    blocks: int
    p_value: float
    reason: str

    @property
    def confidence(self) -> float:
        """1 - p_value: how far the vote is from chance, 0 to 1."""
        return 1.0 - self.p_value

    @property
    def agreeing_share(self) -> float:
        """The share of the votes that agree with the tilts as given, 0 to 1."""
        return (1.0 + self.strength) / 2.0


def undetermined(reason: str) -> ReliefSign:
    """A verdict that decides nothing, for `reason`."""
    return ReliefSign(False, False, "none", 0.0, 0, 1.0, reason)


def combined(occlusion: ReliefSign, lighting: ReliefSign) -> ReliefSign:
    """The images' verdict from both cues: a decisive one decides, both must agree where both are
    decisive (else nothing is decided), occlusion is named where both are."""
    if occlusion.decided and lighting.decided and occlusion.inverted != lighting.inverted:
        return undetermined(
            f"the cues disagree: occlusion says the relief is {_way(occlusion)}, the lighting says {_way(lighting)}"
        )
    for verdict in (occlusion, lighting):
        if verdict.decided:
            return verdict
    reasons = "; ".join(verdict.reason for verdict in (occlusion, lighting) if verdict.reason)
    return undetermined(reasons or "no cue could be used")


def sign_test(agreeing: int, disagreeing: int, *, cue: str, too_few: str, ambiguous: str) -> ReliefSign:
    """The verdict of independent votes for (`agreeing`) and against the tilts as given: decided
    at p < DECISIVE_P_VALUE (two-sided sign test) with MIN_BLOCKS votes or more and |strength|
    at least MIN_STRENGTH; `too_few` and `ambiguous` are the reasons where it is not."""
    votes = agreeing + disagreeing
    if votes < MIN_BLOCKS:
        return undetermined(too_few)
    p_value = float(binomtest(agreeing, votes, 0.5).pvalue)
    strength = (agreeing - disagreeing) / votes
    decided = p_value < DECISIVE_P_VALUE and abs(strength) >= MIN_STRENGTH
    return ReliefSign(disagreeing > agreeing, decided, cue, strength, votes, p_value, "" if decided else ambiguous)


def _way(verdict: ReliefSign) -> str:
    return "inverted" if verdict.inverted else "as the tilts say"
