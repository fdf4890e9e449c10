"""Control on the learned body scheme (paper Sec. III-D) and where to look next.

Jacobian inverse kinematics that reports how sure it is (:mod:`.ik`), active exploration: the next command expected
to teach the learner the most (:mod:`.exploration`, the paper's future work), and moving a real arm safely
(:mod:`.motion`).
"""

from __future__ import annotations

from .exploration import PAPER_NOISE, ExplorationPolicy, NearFocus, excursion_plan, explore_near, in_camera_view
from .ik import IKResult, solve_ik, trained_bounds
from .motion import SafetyLimits, SettleDetector, path_samples, trajectory_duration

__all__ = [
    "IKResult",
    "solve_ik",
    "trained_bounds",
    "ExplorationPolicy",
    "excursion_plan",
    "NearFocus",
    "PAPER_NOISE",
    "explore_near",
    "in_camera_view",
    "trajectory_duration",
    "path_samples",
    "SafetyLimits",
    "SettleDetector",
]
