"""Named exceptions of body_scheme_sim.

All derive from :class:`body_scheme_core.errors.BodySchemeError`, so callers catch the simulator's errors and the
core's with one clause; bad arguments also derive from ``ValueError`` (via ``InvalidInputError``).
"""

from __future__ import annotations

from body_scheme_core.errors import BabblingError, BodySchemeError, FaultScheduleError, InvalidInputError

__all__ = ["SimError", "RobotFileError", "BabblingError", "FaultScheduleError"]


class SimError(BodySchemeError):
    """Base class of every error raised on purpose by body_scheme_sim."""


class RobotFileError(SimError, InvalidInputError):
    """A robot name is unknown, or its URDF or marker file is missing or unreadable."""
