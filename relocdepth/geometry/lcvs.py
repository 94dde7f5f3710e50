"""Loop-closed view synthesis (LCVS, paper Sec. III-C): which views of a triplet are synthesised.

A training sample is a triplet of frames ``(0, 1, 2)``, the middle frame being 1. LCVS warps
every frame into every other one: all 6 ordered ``(target, source)`` pairs, so the relative poses
``T_{t->s}`` of the loop ``0 -> 1 -> 2 -> 0`` are all constrained by the photometric loss. The
"w/o LCVS" ablation keeps monodepth2's 2 pairs into the middle frame. Each pair is warped by
:func:`relocdepth.geometry.warp.warp`.
"""

from __future__ import annotations

# (target, source) frame indices of a triplet: every ordered pair (loop-closed view synthesis).
PAIRS_LCVS: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))
# The "w/o LCVS" ablation: the two neighbours warped into the middle frame.
PAIRS_MIDDLE: tuple[tuple[int, int], ...] = ((1, 0), (1, 2))
