"""Events: every decision of the learner, with its reason, for logs, ROS topics and reports; and how their errors are
written (:func:`format_errors` in reasons, :func:`finite_or_none` in the error fields)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

__all__ = ["Event", "EVENT_KINDS", "format_errors", "finite_or_none"]

#: Kinds of events, in the paper's vocabulary.
EVENT_KINDS = (
    "structure_found",      # the first valid spanning tree (body scheme) was found
    "structure_changed",    # the selected spanning tree changed
    "mismatch_detected",    # a local model of the body scheme stopped matching the observations
    "model_sampled",        # new (temporal) local model(s) instantiated as replacement candidates
    "model_replaced",       # a local model of the body scheme was replaced by a newly learned one
    "model_reinstated",     # a remembered local model fits again and was put back into the body scheme
    "model_retired",        # a local model left the body scheme and went to memory
    "input_rejected",       # an observation or action was rejected (bad value, unknown id, ...)
    "bootstrap_finished",   # learning from scratch ended: the tree's models are frozen, other candidates dropped
    "trust_changed",        # the joint fit's residuals of some part depend on the commands (not trusted), or no more
    "mirror_undone",        # the body scheme held a part's mirror image (its true poses looked flipped): refitted
)


@dataclass(frozen=True)
class Event:
    """One decision of the learner.

    Attributes
    ----------
    step : int
        Time step index (number of ``update`` calls before this one).
    kind : str
        One of :data:`EVENT_KINDS`.
    reason : str
        Human-readable explanation with the numbers behind the decision.
    parent, child : int or None
        Part ids of the local model concerned, if any.
    model : str or None
        Short description of the local model concerned, e.g. ``"gp(1->2 | a0)"``.
    trans_error, rot_error : float or None
        Test-window errors (m, rad) behind the decision, if any.
    """

    step: int
    kind: str
    reason: str
    parent: int | None = None
    child: int | None = None
    model: str | None = None
    trans_error: float | None = None
    rot_error: float | None = None

    def __post_init__(self):
        if self.kind not in EVENT_KINDS:
            raise ValueError(f"unknown event kind {self.kind!r}; known: {EVENT_KINDS}")

    def to_dict(self):
        """Plain dict (JSON-serialisable)."""
        return asdict(self)


def format_errors(trans, rot):
    """``"78 mm / 12.3 deg"`` for a pair of errors in m and rad, as event reasons show them; ``"n/a"`` if one is not
    finite."""
    if not (math.isfinite(trans) and math.isfinite(rot)):
        return "n/a"
    return f"{1000.0 * trans:.0f} mm / {math.degrees(rot):.1f} deg"


def finite_or_none(value):
    """Event error fields: a float, or None where no error is known (keeps events JSON-safe)."""
    value = float(value)
    return value if math.isfinite(value) else None
