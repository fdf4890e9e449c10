"""Fault schedules: ``"step:kind:args"`` strings to faults applied to a :class:`~body_scheme_sim.world.SimWorld`.

A schedule is a list of entries; ``step`` counts executed commands from 0, and a fault scheduled at step ``k``
is applied just before command ``k`` is executed, so command ``k`` is the first one it affects (the core's
``make_session`` convention). Entries (angles in rad, lengths in m, rotation vectors in rad):

==============================================  ==========================================================
``STEP:block_joint:ACTION[:ANGLE]``             the joint of ACTION stops at ANGLE (omitted: where it is)
``STEP:deform_limb:JOINT:DLENGTH[:RX:RY:RZ]``   the limb ending at JOINT grows by DLENGTH, bends by R
``STEP:displace_marker:ID:X:Y:Z[:RX:RY:RZ]``    marker ID moves by (X, Y, Z), turns by R, in its own frame
``STEP:repair[:KIND]``                          undo every fault, or every fault of KIND
==============================================  ==========================================================

Example: ``["150:block_joint:5:0.8", "250:repair", "300:deform_limb:joint6:0.1:0.785:0:0"]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from body_scheme_core.transforms import transform_from_rotvec

from .errors import FaultScheduleError
from .world import FAULT_KINDS

__all__ = ["ScheduledFault", "parse_fault", "parse_fault_schedule", "apply_fault", "delta_from_vector"]

_USAGE = {
    "block_joint": "STEP:block_joint:ACTION[:ANGLE]",
    "deform_limb": "STEP:deform_limb:JOINT:DLENGTH[:RX:RY:RZ]",
    "displace_marker": "STEP:displace_marker:ID:X:Y:Z[:RX:RY:RZ]",
    "repair": "STEP:repair[:KIND]",
}


def delta_from_vector(vector):
    """``old_marker2new_marker`` (4, 4) from ``(x, y, z, rx, ry, rz)``: translation (m) and rotation vector (rad)."""
    vector = np.asarray(vector, dtype=float)
    if vector.shape != (6,) or not np.all(np.isfinite(vector)):
        raise FaultScheduleError(f"a displacement needs 6 finite numbers (x, y, z, rx, ry, rz), got {vector}")
    return transform_from_rotvec(vector[3:], vector[:3])


def apply_fault(world, kind, **params):
    """Apply one fault to ``world`` by kind name.

    Parameters
    ----------
    world : SimWorld
    kind : str
        ``"block_joint"`` (params ``action_index``, ``angle=None``), ``"deform_limb"`` (``joint_name``,
        ``delta_length=0.0``, ``delta_rotvec=(0, 0, 0)``), ``"displace_marker"`` (``marker_id``, ``delta`` (4, 4)) or
        ``"repair"`` (``repair_kind=None``: all).
    """
    if kind == "repair":
        world.repair(params.get("repair_kind"))
    elif kind in FAULT_KINDS:
        getattr(world, kind)(**params)
    else:
        raise FaultScheduleError(f"unknown fault kind {kind!r}; kinds: {list(FAULT_KINDS) + ['repair']}")


@dataclass(frozen=True, eq=False)
class ScheduledFault:
    """One parsed schedule entry; call it with a world to apply it.

    Attributes
    ----------
    step : int
        Index of the first command the fault affects.
    kind : str
    params : dict
        Keyword arguments of :func:`apply_fault`.
    text : str
        The entry it was parsed from.
    """

    step: int
    kind: str
    params: dict = field(default_factory=dict)
    text: str = ""

    def __call__(self, world):
        apply_fault(world, self.kind, **self.params)


def parse_fault(text):
    """Parse one schedule entry ``"step:kind:args"`` (see the module docstring).

    Returns
    -------
    fault : ScheduledFault

    Raises
    ------
    FaultScheduleError
        With the entry, what is wrong and the expected form.
    """
    if not isinstance(text, str):
        raise FaultScheduleError(f"a fault schedule entry must be a string, got {text!r}")
    fields = [part.strip() for part in text.split(":")]
    if len(fields) < 2:
        raise FaultScheduleError(f"fault entry {text!r} needs at least STEP:KIND; kinds: {list(_USAGE)}")
    step_text, kind, args = fields[0], fields[1], fields[2:]
    if kind not in _USAGE:
        raise FaultScheduleError(f"fault entry {text!r}: unknown kind {kind!r}; kinds: {list(_USAGE)}")
    usage = _USAGE[kind]
    try:
        step = int(step_text)
    except ValueError:
        raise FaultScheduleError(f"fault entry {text!r}: step {step_text!r} is not an integer ({usage})") from None
    if step < 0:
        raise FaultScheduleError(f"fault entry {text!r}: step must be >= 0")

    def numbers(values):
        try:
            result = [float(v) for v in values]
        except ValueError:
            raise FaultScheduleError(f"fault entry {text!r}: {values} are not all numbers ({usage})") from None
        if not all(math.isfinite(v) for v in result):
            raise FaultScheduleError(f"fault entry {text!r}: numbers must be finite ({usage})")
        return result

    def integer(value, name):
        try:
            return int(value)
        except ValueError:
            raise FaultScheduleError(f"fault entry {text!r}: {name} {value!r} is not an integer ({usage})") from None

    if kind == "block_joint" and len(args) in (1, 2):
        params = {"action_index": integer(args[0], "ACTION"), "angle": numbers(args[1:])[0] if len(args) == 2
                  else None}
    elif kind == "deform_limb" and len(args) in (2, 5) and args[0]:
        values = numbers(args[1:])
        params = {"joint_name": args[0], "delta_length": values[0],
                  "delta_rotvec": tuple(values[1:]) if len(values) == 4 else (0.0, 0.0, 0.0)}
    elif kind == "displace_marker" and len(args) in (4, 7):
        values = numbers(args[1:]) + [0.0] * (7 - len(args))
        params = {"marker_id": integer(args[0], "ID"), "delta": delta_from_vector(values)}
    elif kind == "repair" and len(args) <= 1:
        repair_kind = args[0] if args else None
        if repair_kind is not None and repair_kind not in FAULT_KINDS:
            raise FaultScheduleError(f"fault entry {text!r}: cannot repair {repair_kind!r}; kinds: {FAULT_KINDS}")
        params = {"repair_kind": repair_kind}
    else:
        raise FaultScheduleError(f"fault entry {text!r} has {len(args)} argument(s); expected {usage}")
    return ScheduledFault(step, kind, params, text)


def parse_fault_schedule(entries):
    """Parse a schedule into ``[(step, fault), ...]`` ordered by step (entries of one step keep their order).

    Parameters
    ----------
    entries : iterable of str

    Returns
    -------
    schedule : list of (int, ScheduledFault)
        ``fault(world)`` applies the fault.
    """
    if isinstance(entries, str):
        raise FaultScheduleError(f"a fault schedule is a list of entries, got the string {entries!r}")
    faults = [parse_fault(entry) for entry in entries]
    return [(fault.step, fault) for fault in sorted(faults, key=lambda fault: fault.step)]
