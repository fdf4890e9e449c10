"""Faults: changes of the robot's physiology at a time step, their schedule entries, and the paper's protocols.

A :class:`Fault` is applied to a :class:`~body_scheme_core.world.body.Body` here (synthetic sessions) and to a
:class:`body_scheme_sim.world.SimWorld` by the simulator (``SimWorld.apply``), so both worlds break the same way.
Schedules are lists of ``"step:kind:args"`` entries (angles in rad, lengths in m, rotation vectors in rad):

==============================================  ==========================================================
``STEP:block_joint:ACTION[:ANGLE]``             the joint of ACTION stops at ANGLE (omitted: where it is)
``STEP:deform_limb:JOINT:DLENGTH[:RX:RY:RZ]``   the limb ending at JOINT grows by DLENGTH, bends by R
``STEP:displace_marker:ID:X:Y:Z[:RX:RY:RZ]``    marker ID moves by (X, Y, Z), turns by R, in its own frame
``STEP:repair[:KIND]``                          undo every fault, or every fault of KIND
==============================================  ==========================================================

A fault scheduled at step ``k`` affects command ``k`` and later ones. Example:
``["150:block_joint:5:0.8", "250:repair", "300:deform_limb:joint6:0.1:0.785:0:0"]``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import FaultScheduleError, InvalidInputError
from ..transforms import transform_from_rotvec
from .body import block_joint, deform_limb, displace_marker

__all__ = ["Fault", "REPAIR", "FAULT_KINDS", "parse_fault", "parse_fault_schedule", "delta_from_vector",
           "PROTOCOL_FAULTS", "protocol_schedule", "RANDOM_FAULTS", "random_fault"]

#: Kinds of faults that change the body (``"repair"`` undoes them).
FAULT_KINDS = ("block_joint", "deform_limb", "displace_marker")
_USAGE = {
    "block_joint": "STEP:block_joint:ACTION[:ANGLE]",
    "deform_limb": "STEP:deform_limb:JOINT:DLENGTH[:RX:RY:RZ]",
    "displace_marker": "STEP:displace_marker:ID:X:Y:Z[:RX:RY:RZ]",
    "repair": "STEP:repair[:KIND]",
}


class Fault:
    """A change of the robot's physiology.

    Parameters
    ----------
    kind : str
        ``"block_joint"`` (params ``action_index``, ``angle``; ``None``: where the joint is), ``"deform_limb"``
        (``joint_or_link``, ``delta_length``, ``delta_rotvec``), ``"displace_marker"`` (``marker_id``, ``delta``
        (4, 4)): the functions of :mod:`body_scheme_core.world.body` of the same names, applied to the current body
        so faults accumulate; or ``"repair"`` (``repair_kind``: ``None`` for all faults, or one kind).
    **params
    """

    KINDS = (*FAULT_KINDS, "repair")

    def __init__(self, kind, **params):
        if kind not in self.KINDS:
            raise InvalidInputError(f"fault kind must be one of {self.KINDS}, got {kind!r}")
        self.kind = kind
        self.params = params

    def apply(self, current, original):
        """The body after the fault, from the ``current`` and the ``original`` body.

        Raises
        ------
        InvalidInputError
            For the two forms only a world that remembers its joint positions and faults can apply (a block without
            an angle, a repair of one kind): ``SimWorld.apply``.
        """
        if self.kind == "repair":
            if self.params.get("repair_kind") is not None:
                raise InvalidInputError(f"{self.entry} needs the fault history; SimWorld.apply does it")
            return original
        if self.kind == "block_joint" and self.params.get("angle") is None:
            raise InvalidInputError(f"{self.entry} holds the joint where it is; give an angle, or SimWorld.apply")
        function = {"block_joint": block_joint, "deform_limb": deform_limb, "displace_marker": displace_marker}
        return function[self.kind](current, **self.params)

    @property
    def entry(self):
        """The fault as a schedule entry without its step: ``"block_joint:5:0.8"``, ``"repair"``, ..."""
        p = self.params
        if self.kind == "repair":
            return "repair" if p.get("repair_kind") is None else f"repair:{p['repair_kind']}"
        if self.kind == "block_joint":
            angle = p.get("angle")
            return f"block_joint:{p['action_index']}" + ("" if angle is None else f":{angle}")
        if self.kind == "deform_limb":
            numbers = (p.get("delta_length", 0.0), *p.get("delta_rotvec", (0.0, 0.0, 0.0)))
            return f"deform_limb:{p['joint_or_link']}:" + ":".join(repr(float(v)) for v in numbers)
        delta = np.asarray(p["delta"], dtype=float)
        numbers = (*delta[:3, 3], *Rotation.from_matrix(delta[:3, :3]).as_rotvec())
        return f"displace_marker:{p['marker_id']}:" + ":".join(repr(float(v)) for v in numbers)

    def describe(self):
        """Short text like ``block_joint(action_index=5, angle=0.8)``."""
        args = ", ".join(f"{k}={np.asarray(v).round(4).tolist() if not np.isscalar(v) else v}"
                         for k, v in self.params.items())
        return f"{self.kind}({args})"

    def __repr__(self):
        return f"<Fault {self.describe()}>"


def delta_from_vector(vector):
    """``old_marker2new_marker`` (4, 4) from ``(x, y, z, rx, ry, rz)``: translation (m) and rotation vector (rad)."""
    vector = np.asarray(vector, dtype=float)
    if vector.shape != (6,) or not np.all(np.isfinite(vector)):
        raise FaultScheduleError(f"a displacement needs 6 finite numbers (x, y, z, rx, ry, rz), got {vector}")
    return transform_from_rotvec(vector[3:], vector[:3])


def parse_fault(text):
    """Parse one schedule entry ``"step:kind:args"`` (see the module docstring).

    Returns
    -------
    step : int
    fault : Fault

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
        params = {"joint_or_link": args[0], "delta_length": values[0],
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
    return step, Fault(kind, **params)


def parse_fault_schedule(entries):
    """Parse a schedule into ``[(step, fault), ...]`` ordered by step (entries of one step keep their order).

    Parameters
    ----------
    entries : iterable of str
    """
    if isinstance(entries, str):
        raise FaultScheduleError(f"a fault schedule is a list of entries, got the string {entries!r}")
    return sorted((parse_fault(entry) for entry in entries), key=lambda item: item[0])


#: Restores the original body.
REPAIR = Fault("repair")


#: The paper's adaptation protocols (Sec. IV-B/C) on :func:`powercube_6dof`: name -> the fault of blocks 2 and 4.
#: Block 1 is normal, block 3 repaired. Defined once here; the simulator records the same schedule
#: (:func:`body_scheme_sim.sessions.record_protocol`) from :attr:`Fault.entry`.
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


#: What :func:`random_fault` can do to a body: the four changes of physiology the paper names.
RANDOM_FAULTS = ("block_joint", "bend_limb", "move_marker", "add_tool")


def _observed_below(tree, joint):
    """Whether a marker sits on ``joint``'s child link or below it."""
    below = {joint.child}
    changed = True
    while changed:
        changed = False
        for other in tree.joints:
            if other.parent in below and other.child not in below:
                below.add(other.child)
                changed = True
    return any(m.link in below for m in tree.markers)


def random_fault(tree, kind, rng, size):
    """A random change of ``tree``'s physiology that moves observed markers by about ``size`` or more.

    Parameters
    ----------
    tree : KinematicTree
    kind : str
        One of :data:`RANDOM_FAULTS`: ``block_joint`` (a commanded joint that moves a marker stops somewhere in the
        middle half of its range), ``bend_limb`` (a limb above a marker bends by 20 deg about a random axis),
        ``move_marker`` (a marker slides ``size`` m in a random direction on its link) or ``add_tool`` (the limb of a
        joint with markers below it and none below those grows by ``size`` m, like a tool in the gripper).
    rng : numpy.random.Generator
    size : float
        Smallest displacement, m: e.g. three times the noise RMS, so the change is detectable.

    Returns
    -------
    fault : Fault

    Raises
    ------
    InvalidInputError
        If the tree has nothing the fault can act on (e.g. no commanded joint moving a marker).
    """
    if kind not in RANDOM_FAULTS:
        raise InvalidInputError(f"kind must be one of {RANDOM_FAULTS}, got {kind!r}")
    observed = [j for j in tree.joints if _observed_below(tree, j)]
    if kind == "move_marker":
        direction = rng.normal(size=3)
        delta = np.eye(4)
        delta[:3, 3] = size * direction / np.linalg.norm(direction)
        return Fault("displace_marker", marker_id=int(rng.choice(tree.marker_ids)), delta=delta)
    if kind == "block_joint":
        joints = [j for j in observed if j.action is not None]
        if not joints:
            raise InvalidInputError(f"{tree!r} has no commanded joint that moves a marker")
        joint = joints[int(rng.integers(len(joints)))]
        middle, half = 0.5 * (joint.lower + joint.upper), 0.25 * (joint.upper - joint.lower)
        return Fault("block_joint", action_index=joint.action, angle=float(rng.uniform(middle - half, middle + half)))
    if kind == "bend_limb":
        joints = [j for j in observed if np.linalg.norm(j.origin[:3, 3]) > 1e-3]
        if not joints:
            raise InvalidInputError(f"{tree!r} has no limb above a marker")
        axis = rng.normal(size=3)
        return Fault("deform_limb", joint_or_link=joints[int(rng.integers(len(joints)))].name, delta_length=0.0,
                     delta_rotvec=tuple(math.radians(20.0) * axis / np.linalg.norm(axis)))
    # add_tool: a last limb (markers on its link, none further out) that is long enough to grow along.
    parents = {j.parent for j in observed}
    joints = [j for j in observed if j.child not in parents and np.linalg.norm(j.origin[:3, 3]) > 1e-3]
    if not joints:
        raise InvalidInputError(f"{tree!r} has no last limb with a marker")
    return Fault("deform_limb", joint_or_link=joints[int(rng.integers(len(joints)))].name, delta_length=float(size),
                 delta_rotvec=(0.0, 0.0, 0.0))
