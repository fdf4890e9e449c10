"""Faults: changes of the robot's physiology at a time step, and the paper's adaptation protocols.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InvalidInputError
from .body import block_joint, deform_limb, displace_marker

__all__ = ["Fault", "REPAIR", "PROTOCOL_FAULTS", "protocol_schedule"]


class Fault:
    """A change of the robot's physiology at a time step of a session.

    Parameters
    ----------
    kind : str
        ``"block_joint"``, ``"deform_limb"``, ``"displace_marker"`` (the functions of the same names, applied to
        the current body, so faults accumulate) or ``"repair"`` (back to the original body).
    **params
        Keyword arguments of that function (besides ``body``).
    """

    KINDS = ("block_joint", "deform_limb", "displace_marker", "repair")

    def __init__(self, kind, **params):
        if kind not in self.KINDS:
            raise InvalidInputError(f"fault kind must be one of {self.KINDS}, got {kind!r}")
        self.kind = kind
        self.params = params

    def apply(self, current, original):
        """The body after the fault, from the ``current`` and the ``original`` body."""
        if self.kind == "repair":
            return original
        function = {"block_joint": block_joint, "deform_limb": deform_limb, "displace_marker": displace_marker}
        return function[self.kind](current, **self.params)

    @property
    def entry(self):
        """The fault as a simulator schedule entry without its step (``"block_joint:5:0.8"``, ``"repair"``; see
        :mod:`body_scheme_sim.faults`).

        Raises
        ------
        InvalidInputError
            For a fault the schedule syntax cannot express (a marker displacement given as a matrix).
        """
        p = self.params
        if self.kind == "repair":
            return "repair"
        if self.kind == "block_joint":
            return f"block_joint:{p['action_index']}:{p['angle']}"
        if self.kind == "deform_limb":
            numbers = (p.get("delta_length", 0.0), *p.get("delta_rotvec", (0.0, 0.0, 0.0)))
            return f"deform_limb:{p['joint_or_link']}:" + ":".join(repr(float(v)) for v in numbers)
        raise InvalidInputError(f"{self.describe()} has no schedule entry form")

    def describe(self):
        """Short text like ``block_joint(action_index=5, angle=0.8)``."""
        args = ", ".join(f"{k}={np.asarray(v).round(4).tolist() if not np.isscalar(v) else v}"
                         for k, v in self.params.items())
        return f"{self.kind}({args})"

    def __repr__(self):
        return f"<Fault {self.describe()}>"


#: Restores the original body.
REPAIR = Fault("repair")


#: The paper's adaptation protocols (Sec. IV-B/C) on :func:`powercube_6dof`: name -> the fault of blocks 2 and 4.
#: Block 1 is normal, block 3 repaired. Defined once here; the simulator records the same schedule
#: (:func:`body_scheme_sim.sessions.record_protocol`) from :meth:`Fault.entry`.
PROTOCOL_FAULTS = {
    "joint_blocked": lambda: Fault("block_joint", action_index=5, angle=0.8),
    "limb_deformed": lambda: Fault("deform_limb", joint_or_link="tool_joint", delta_length=0.1,
                                   delta_rotvec=(math.pi / 4, 0.0, 0.0)),
}


def protocol_schedule(protocol, n_per_block=100, fault=None):
    """The fault schedule of a protocol: ``[(n, fault), (2n, REPAIR), (3n, fault)]``.

    Parameters
    ----------
    protocol : str
        A key of :data:`PROTOCOL_FAULTS`.
    n_per_block : int
    fault : Fault or None
        Replaces the protocol's own fault (e.g. another blocked angle).
    """
    if protocol not in PROTOCOL_FAULTS:
        raise InvalidInputError(f"protocol must be one of {list(PROTOCOL_FAULTS)}, got {protocol!r}")
    fault = PROTOCOL_FAULTS[protocol]() if fault is None else fault
    n = n_per_block
    return [(n, fault), (2 * n, REPAIR), (3 * n, fault)]
