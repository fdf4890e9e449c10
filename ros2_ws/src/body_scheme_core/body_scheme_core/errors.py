"""Named exceptions of body_scheme_core.

Every error the library raises on purpose derives from :class:`BodySchemeError`, so callers (the ROS nodes) can
catch ours without swallowing programming errors. Input validation errors also derive from ``ValueError``.
"""

from __future__ import annotations

__all__ = ["BodySchemeError", "InvalidInputError", "ModelFileError", "NotFittedError", "BabblingError",
           "FaultScheduleError", "ActionOutOfRangeError", "StampOrderError", "LearnerStepError"]


class BodySchemeError(Exception):
    """Base class of every error raised on purpose by body_scheme_core."""


class InvalidInputError(BodySchemeError, ValueError):
    """An argument has the wrong shape, is not finite, or is not a valid pose, id or configuration."""


class ModelFileError(BodySchemeError):
    """A saved state file is corrupt, truncated, of another format, or of an unsupported version."""


class NotFittedError(BodySchemeError):
    """A local model was asked to predict before it was fitted."""


class BabblingError(BodySchemeError):
    """Motor babbling found too few valid configurations within its budget of tries."""


class FaultScheduleError(InvalidInputError):
    """A fault schedule entry (``"step:kind:args"``) cannot be parsed."""


class ActionOutOfRangeError(InvalidInputError):
    """An action is beyond the joint limits by more than the configured margin."""


class StampOrderError(InvalidInputError):
    """A time step is stamped before the previous one (for a node: older than the state it restored)."""


class LearnerStepError(BodySchemeError):
    """A time step failed inside the learner (a defect, not bad input): the step was undone, the learner is exactly as
    it was before the call, and the error it met is the ``__cause__``. The caller may go on with the next step."""
