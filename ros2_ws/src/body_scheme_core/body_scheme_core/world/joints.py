"""The parts of a kinematic tree (:class:`~body_scheme_core.world.tree.KinematicTree`, whose docstring states the
conventions): a joint between two links, as URDF has it, and a marker on a link.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..transforms import check_transform, transform_from_xyz_rpy, xyz_rpy_from_transform

__all__ = ["JOINT_TYPES", "MOVABLE_JOINT_TYPES", "CONTINUOUS_RANGE", "AXIS_NORM_TOLERANCE", "Joint", "Marker"]


JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")
#: Joint types that move with their action.
MOVABLE_JOINT_TYPES = ("revolute", "continuous", "prismatic")
#: Position range given to continuous joints (and revolute joints whose URDF limits are unset), rad.
CONTINUOUS_RANGE = (-math.pi, math.pi)
#: Largest accepted deviation of a joint axis norm from 1.
AXIS_NORM_TOLERANCE = 1e-6


def _frozen_array(value, shape, name):
    array = np.array(value, dtype=float)
    if array.shape != shape:
        raise InvalidInputError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise InvalidInputError(f"{name} contains NaN or inf")
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class Joint:
    """One joint of a kinematic tree (URDF semantics).

    Attributes
    ----------
    name : str
    type : str
        One of :data:`JOINT_TYPES`.
    parent, child : str
        Link names.
    origin : ndarray, shape (4, 4)
        ``parent_link2joint_frame`` at zero position (read-only).
    axis : ndarray, shape (3,)
        Unit axis of rotation or translation in the joint frame (read-only).
    lower, upper : float
        Position limits (rad or m); actions are drawn and clipped within them.
    action : int or None
        Index into the action vector that commands the joint; ``None`` for fixed and passive joints.
    mimic : str or None
        Name of the joint this one mimics (it then shares that joint's ``action``); ``None`` for other joints.
    multiplier, offset : float
        Joint position ``multiplier * a[action] + offset`` (1 and 0 unless ``mimic`` is set).
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    axis: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    lower: float = CONTINUOUS_RANGE[0]
    upper: float = CONTINUOUS_RANGE[1]
    action: int | None = None
    mimic: str | None = None
    multiplier: float = 1.0
    offset: float = 0.0

    def __post_init__(self):
        if self.type not in JOINT_TYPES:
            raise InvalidInputError(f"joint {self.name!r}: type must be one of {JOINT_TYPES}, got {self.type!r}")
        for field in ("name", "parent", "child"):
            if not isinstance(getattr(self, field), str) or not getattr(self, field):
                raise InvalidInputError(f"joint {field} must be a non-empty string, got {getattr(self, field)!r}")
        if self.parent == self.child:
            raise InvalidInputError(f"joint {self.name!r} connects link {self.parent!r} to itself")
        origin = _frozen_array(self.origin, (4, 4), f"joint {self.name!r} origin")
        check_transform(origin, name=f"joint {self.name!r} origin")
        axis = _frozen_array(self.axis, (3,), f"joint {self.name!r} axis")
        if abs(np.linalg.norm(axis) - 1.0) > AXIS_NORM_TOLERANCE:
            raise InvalidInputError(f"joint {self.name!r} axis must be a unit vector, got {axis.tolist()}")
        lower, upper = float(self.lower), float(self.upper)
        if not (math.isfinite(lower) and math.isfinite(upper) and lower <= upper):
            raise InvalidInputError(f"joint {self.name!r} needs finite limits lower <= upper, got {lower}, {upper}")
        action = self.action
        if action is not None:
            if isinstance(action, bool) or int(action) != action or int(action) < 0:
                raise InvalidInputError(f"joint {self.name!r} action must be an integer >= 0, got {action!r}")
            action = int(action)
            if self.type == "fixed":
                raise InvalidInputError(f"fixed joint {self.name!r} cannot be commanded by action {action}")
        multiplier, offset = float(self.multiplier), float(self.offset)
        if not (math.isfinite(multiplier) and math.isfinite(offset)):
            raise InvalidInputError(f"joint {self.name!r} needs a finite multiplier and offset, got {multiplier}, "
                                    f"{offset}")
        if self.mimic is None and (multiplier, offset) != (1.0, 0.0):
            raise InvalidInputError(f"joint {self.name!r}: only a mimic joint has a multiplier and offset")
        if self.mimic is not None and (not isinstance(self.mimic, str) or self.mimic in ("", self.name)
                                       or self.type == "fixed"):
            raise InvalidInputError(f"joint {self.name!r} cannot mimic {self.mimic!r}")
        object.__setattr__(self, "multiplier", multiplier)
        object.__setattr__(self, "offset", offset)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "axis", axis)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "action", action)

    @property
    def is_movable(self):
        """Whether the joint has a degree of freedom (it may still be passive, ``action is None``)."""
        return self.type in MOVABLE_JOINT_TYPES

    def position(self, A):
        """The joint's positions for action vectors ``A`` (n, m): its action scaled for a mimic joint, zero for a
        fixed or passive joint (a mimic of a passive joint: its offset); shape (n,)."""
        if self.action is None:
            return np.full(A.shape[0], self.offset)
        return self.multiplier * A[:, self.action] + self.offset

    def motion(self, q):
        """``joint_frame2child_link`` for joint position(s) ``q``.

        Parameters
        ----------
        q : float or array-like, shape (n,)

        Returns
        -------
        T : ndarray, shape (4, 4) or (n, 4, 4)
        """
        q = np.asarray(q, dtype=float)
        flat = np.atleast_1d(q)
        T = np.tile(np.eye(4), (flat.shape[0], 1, 1))
        if self.type in ("revolute", "continuous"):
            T[:, :3, :3] = Rotation.from_rotvec(flat[:, None] * self.axis[None, :]).as_matrix()
        elif self.type == "prismatic":
            T[:, :3, 3] = flat[:, None] * self.axis[None, :]
        return T[0] if q.ndim == 0 else T

    def transform(self, q):
        """``parent_link2child_link = origin @ motion(q)``, shape (4, 4) or (n, 4, 4)."""
        return self.origin @ self.motion(q)

    def to_dict(self):
        """JSON-serialisable dict."""
        return {"name": self.name, "type": self.type, "parent": self.parent, "child": self.child,
                "origin": self.origin.tolist(), "axis": self.axis.tolist(), "lower": self.lower,
                "upper": self.upper, "action": self.action, "mimic": self.mimic, "multiplier": self.multiplier,
                "offset": self.offset}

    @classmethod
    def from_dict(cls, data):
        """Inverse of :meth:`to_dict`."""
        return cls(**data)


@dataclass(frozen=True, eq=False)
class Marker:
    """A visual marker rigidly attached to a link: one observable body part.

    Attributes
    ----------
    id : int
        Marker id = body-part id.
    link : str
        Link it is attached to.
    link2marker : ndarray, shape (4, 4)
        Pose of the marker in the link frame (read-only). The marker's z axis is its outward normal.
    size : float
        Edge length of the square marker, m.
    plate : int or None
        The id of the plate the marker is glued on with others (:mod:`body_scheme_core.plates`): the id of one of
        them, the plate's reference, whose pose the plate's is; None: a marker of its own.
    """

    id: int
    link: str
    link2marker: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    size: float = 0.05
    plate: int | None = None

    def __post_init__(self):
        if isinstance(self.id, bool) or not isinstance(self.id, (int, np.integer)) or int(self.id) < 0:
            raise InvalidInputError(f"marker id must be an integer >= 0, got {self.id!r}")
        if not isinstance(self.link, str) or not self.link:
            raise InvalidInputError(f"marker {self.id} link must be a non-empty string, got {self.link!r}")
        link2marker = np.array(check_transform(self.link2marker, name=f"marker {self.id} link2marker"))
        link2marker.flags.writeable = False
        size = float(self.size)
        if not (math.isfinite(size) and size > 0):
            raise InvalidInputError(f"marker {self.id} size must be a finite number > 0, got {self.size!r}")
        if self.plate is not None and (isinstance(self.plate, bool) or not isinstance(self.plate, (int, np.integer))
                                       or int(self.plate) < 0):
            raise InvalidInputError(f"marker {self.id} plate must be a marker id (an integer >= 0), got {self.plate!r}")
        object.__setattr__(self, "id", int(self.id))
        object.__setattr__(self, "link2marker", link2marker)
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "plate", None if self.plate is None else int(self.plate))

    def to_dict(self):
        """Marker file entry ``{id, link, xyz, rpy, size[, plate]}`` (plain floats)."""
        xyz, rpy = xyz_rpy_from_transform(self.link2marker)
        entry = {"id": self.id, "link": self.link, "xyz": [float(v) for v in xyz], "rpy": [float(v) for v in rpy],
                 "size": self.size}
        return entry if self.plate is None else {**entry, "plate": self.plate}

    @classmethod
    def from_dict(cls, data):
        """Build from a marker file entry ``{id, link, xyz, rpy, size, plate}`` (all but ``id``, ``link`` optional)."""
        if not isinstance(data, dict):
            raise InvalidInputError(f"a marker entry must be a mapping, got {data!r}")
        unknown = sorted(set(data) - {"id", "link", "xyz", "rpy", "size", "plate"})
        if unknown or "id" not in data or "link" not in data:
            raise InvalidInputError(f"a marker entry needs keys id, link and may have xyz, rpy, size, plate; got "
                                    f"{data!r}")
        link2marker = transform_from_xyz_rpy(data.get("xyz", [0.0, 0.0, 0.0]), data.get("rpy", [0.0, 0.0, 0.0]))
        return cls(id=data["id"], link=data["link"], link2marker=link2marker, size=data.get("size", 0.05),
                   plate=data.get("plate"))
