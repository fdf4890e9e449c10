"""scheme_node's settings in one place, without ROS: defaults, parsing and validation, and what they build.

The node declares one ROS parameter per entry of :func:`parameter_defaults` and passes their values to
:meth:`SchemeSettings.from_parameters`; the offline replay reads the same YAML file through
:meth:`SchemeSettings.from_yaml`. Both then build the learner and the pairer with the same code, so a bag replayed
through the ROS graph and one replayed offline see identical settings.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import re
from dataclasses import dataclass

import yaml

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.learning import BodySchemeConfig, BodySchemeLearner
from body_scheme_core.models import engineered_models
from body_scheme_core.pairing import CommandObservationPairer
from body_scheme_core.world import KinematicTree, load_markers_yaml

from .message_feed import MessageLimits

__all__ = ["LEARNER_PREFIX", "NONE_SENTINELS", "AUTO_SENTINELS", "URDF_TOLERANCE", "SchemeSettings",
           "engineered_body_scheme", "specification_tree", "parameter_defaults", "robot_parameter_file"]

#: How far a robot may be from its URDF by default (m, rad): a chain between two markers with unmarked links between
#: them is calibrated from there (assembly of a few mm, zero offsets of a degree).
URDF_TOLERANCE = (0.005, math.radians(1.0))
#: ROS parameter prefix of the BodySchemeConfig fields.
LEARNER_PREFIX = "learner."
#: Optional config fields that ROS parameters cannot hold as None: this value stands for None.
NONE_SENTINELS = {"theta_trans": 0.0, "theta_rot": 0.0, "root": -1}
#: Noise priors that a ROS double parameter cannot hold as "auto": 0.0 stands for "auto" (learned from the start).
AUTO_SENTINELS = {"sigma_trans": 0.0, "sigma_rot": 0.0}


def parameter_defaults(n_joints=1):
    """Every scheme_node parameter with its typed default (``action_*`` defaults depend on the joint count)."""
    defaults = {
        "part_ids": [0], "joint_names": [f"joint_{k}" for k in range(n_joints)],
        "action_lower": [-math.pi] * n_joints, "action_upper": [math.pi] * n_joints,
        "frame_id": "camera", "update_period": 0.02,
        "settle_time": 0.0, "max_delay": 2.0, "pairing_grace": 0.2,
        "checkpoint_path": "", "checkpoint_period": 30.0, "urdf_path": "", "markers_path": "",
        "urdf_tolerance_trans": URDF_TOLERANCE[0], "urdf_tolerance_rot": URDF_TOLERANCE[1],
        "stamp_tolerance": 1.0, "unstamped_policy": "receipt_time", "stall_timeout": 10.0, "hardware_id": "",
        "state_dir": "", "max_state_bytes": 64 * 1024 * 1024,
        "queue_depth": 1000, "max_inbox": 2000, "max_pending_samples": 500, "max_sample_age": 5.0,
        "tf_prefix": "", "view_period": 0.1, "exploration": False, "exploration_candidates": 64,
        "exploration_travel_weight": 0.0, "exploration_camera_info": "", "exploration_excursions": False,
        "max_message_bytes": MessageLimits().max_bytes, "max_joint_names": MessageLimits().max_joint_names,
        "max_markers": MessageLimits().max_markers, "service_queue_depth": 100, "max_waiting_requests": 20,
    }
    config = BodySchemeConfig()
    for field in dataclasses.fields(BodySchemeConfig):
        value = getattr(config, field.name)
        if field.name in NONE_SENTINELS:
            value = NONE_SENTINELS[field.name]
        if field.name in AUTO_SENTINELS and value == "auto":
            value = AUTO_SENTINELS[field.name]
        defaults[LEARNER_PREFIX + field.name] = list(value) if isinstance(value, tuple) else value
    return defaults


#: Largest value of each integer setting: a queue depth is memory reserved per message, a byte limit memory per file.
INTEGER_BOUNDS = {"max_state_bytes": 1 << 31, "queue_depth": 100_000, "max_inbox": 1_000_000,
                  "max_pending_samples": 1_000_000, "max_message_bytes": 1 << 30, "max_joint_names": 100_000,
                  "max_markers": 1_000_000, "service_queue_depth": 10_000, "max_waiting_requests": 10_000}
#: A TF frame prefix: names of letters, digits and underscores, joined by single slashes (no leading slash).
TF_PREFIX = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*/?")
#: Directories of the kernel and devices: no state, checkpoint or robot file lives there.
SPECIAL_DIRECTORIES = ("/proc", "/sys", "/dev")


def _special_path_problem(path):
    """Why ``path`` cannot be one of our files or directories (a special directory, a NUL byte), or None."""
    if not path:
        return None
    if "\0" in path:
        return "contains a NUL byte"
    resolved = os.path.realpath(os.path.expanduser(path))
    if any(resolved == d or resolved.startswith(d + "/") for d in SPECIAL_DIRECTORIES):
        return f"resolves to {resolved}, inside {', '.join(SPECIAL_DIRECTORIES)}: not a place for our files"
    return None


@dataclass(frozen=True)
class SchemeSettings:
    """Validated settings of scheme_node (see docs/nodes.md for each one)."""

    part_ids: tuple
    joint_names: tuple
    action_lower: tuple
    action_upper: tuple
    config: BodySchemeConfig
    frame_id: str = "camera"
    update_period: float = 0.02
    settle_time: float = 0.0
    max_delay: float = 2.0
    pairing_grace: float = 0.2
    checkpoint_path: str = ""
    checkpoint_period: float = 30.0
    urdf_path: str = ""
    markers_path: str = ""
    urdf_tolerance_trans: float = URDF_TOLERANCE[0]
    urdf_tolerance_rot: float = URDF_TOLERANCE[1]
    stamp_tolerance: float = 1.0
    unstamped_policy: str = "receipt_time"
    stall_timeout: float = 10.0
    hardware_id: str = ""
    state_dir: str = ""
    max_state_bytes: int = 64 * 1024 * 1024
    queue_depth: int = 1000
    max_inbox: int = 2000
    max_pending_samples: int = 500
    max_sample_age: float = 5.0
    tf_prefix: str = ""
    view_period: float = 0.1
    max_message_bytes: int = MessageLimits().max_bytes
    max_joint_names: int = MessageLimits().max_joint_names
    max_markers: int = MessageLimits().max_markers
    service_queue_depth: int = 100
    max_waiting_requests: int = 20
    exploration: bool = False
    exploration_candidates: int = 64
    exploration_travel_weight: float = 0.0
    exploration_camera_info: str = ""
    exploration_excursions: bool = False

    #: What scheme_node does with a zero-stamped message: stamp it with its receipt time, or refuse it.
    UNSTAMPED_POLICIES = ("receipt_time", "reject")

    def __post_init__(self):
        m = len(self.joint_names)
        if m == 0 or len(set(self.joint_names)) != m:
            raise InvalidInputError(f"joint_names must be non-empty and unique, got {list(self.joint_names)}")
        if len(self.action_lower) != m or len(self.action_upper) != m:
            raise InvalidInputError(f"action_lower/action_upper need {m} values (one per joint name), got "
                                    f"{len(self.action_lower)} and {len(self.action_upper)}")
        if len(self.part_ids) < 2 or len(set(self.part_ids)) != len(self.part_ids):
            raise InvalidInputError(f"part_ids must name at least two distinct parts, got {list(self.part_ids)}")
        for name in ("update_period", "stamp_tolerance", "stall_timeout", "max_sample_age",
                     "view_period"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidInputError(f"{name} must be a finite number > 0 s, got {value!r}")
        if not (isinstance(self.checkpoint_period, (int, float)) and math.isfinite(self.checkpoint_period)
                and self.checkpoint_period > 0):
            raise InvalidInputError(f"checkpoint_period must be a finite number > 0 s (checkpoint_path \"\" turns "
                                    f"checkpoints off), got {self.checkpoint_period!r}")
        for name, largest in INTEGER_BOUNDS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= largest:
                raise InvalidInputError(f"{name} must be an integer from 1 to {largest:,}, got {value!r}")
        if len(self.joint_names) > self.max_joint_names:
            raise InvalidInputError(f"{len(self.joint_names)} joint_names, but max_joint_names is "
                                    f"{self.max_joint_names}: a command naming them all would be refused")
        if len(self.part_ids) > self.max_markers:
            raise InvalidInputError(f"{len(self.part_ids)} part_ids, but max_markers is {self.max_markers}")
        if self.tf_prefix and not TF_PREFIX.fullmatch(self.tf_prefix):
            raise InvalidInputError(f"tf_prefix must be a TF frame prefix: names of letters, digits and _ joined by "
                                    f"single /, no leading / (e.g. \"robot_a\" or \"lab/robot_a\"), got "
                                    f"{self.tf_prefix!r}")
        for name in ("frame_id", "hardware_id"):
            value = getattr(self, name)
            if len(value) > 256 or any(not ch.isprintable() for ch in value):
                raise InvalidInputError(f"{name} must be printable and at most 256 characters, got {value[:80]!r}")
        for name in ("state_dir", "checkpoint_path", "urdf_path", "markers_path"):
            problem = _special_path_problem(getattr(self, name))
            if problem:
                raise InvalidInputError(f"{name} {getattr(self, name)!r}: {problem}")
        for name in ("urdf_tolerance_trans", "urdf_tolerance_rot"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value <= 1.0):
                raise InvalidInputError(f"{name} must be a number from 0 to 1 (m or rad; 0 for both: the URDF "
                                        f"exact), got {value!r}")
        for name in ("exploration", "exploration_excursions"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidInputError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if isinstance(self.exploration_candidates, bool) or not isinstance(self.exploration_candidates, int) or \
                not 1 <= self.exploration_candidates <= 100_000:
            raise InvalidInputError(f"exploration_candidates must be an integer from 1 to 100,000, got "
                                    f"{self.exploration_candidates!r}")
        if not (isinstance(self.exploration_travel_weight, (int, float))
                and math.isfinite(self.exploration_travel_weight) and self.exploration_travel_weight >= 0):
            raise InvalidInputError(f"exploration_travel_weight must be a number >= 0, got "
                                    f"{self.exploration_travel_weight!r}")
        if not isinstance(self.exploration_camera_info, str):
            raise InvalidInputError(f"exploration_camera_info must be a topic name or \"\", got "
                                    f"{self.exploration_camera_info!r}")
        if self.unstamped_policy not in self.UNSTAMPED_POLICIES:
            raise InvalidInputError(f"unstamped_policy must be one of {self.UNSTAMPED_POLICIES}, got "
                                    f"{self.unstamped_policy!r}")

    @classmethod
    def from_parameters(cls, values):
        """Build from ``{parameter name: value}``; missing names take :func:`parameter_defaults`."""
        defaults = parameter_defaults(len(values.get("joint_names", [None])))
        unknown = sorted(set(values) - set(defaults))
        if unknown:
            raise InvalidInputError(f"unknown scheme_node parameter(s) {unknown}; known: {sorted(defaults)}")
        merged = dict(defaults, **values)
        learner = {}
        for name, value in merged.items():
            if name.startswith(LEARNER_PREFIX):
                field = name[len(LEARNER_PREFIX):]
                if field in NONE_SENTINELS and value == NONE_SENTINELS[field]:
                    value = None
                elif field in AUTO_SENTINELS and value in (AUTO_SENTINELS[field], "auto"):
                    value = "auto"
                learner[field] = value
        plain = {k: v for k, v in merged.items() if not k.startswith(LEARNER_PREFIX)}
        lists = {}
        for name, kind in (("part_ids", int), ("joint_names", str), ("action_lower", float), ("action_upper", float)):
            value = plain.pop(name)
            try:  # an empty list in a YAML file arrives untyped, as None
                lists[name] = tuple(kind(v) for v in ([] if value is None else value))
            except (TypeError, ValueError) as error:
                raise InvalidInputError(f"{name} must be a list of {kind.__name__}, got {value!r} ({error})") from None
        for name, default in parameter_defaults(len(lists["joint_names"]) or 1).items():
            if name in plain and type(plain[name]) is not type(default) and not (
                    isinstance(default, float) and isinstance(plain[name], int) and not isinstance(plain[name], bool)):
                raise InvalidInputError(f"{name} must be a {type(default).__name__}, got {plain[name]!r}")
        return cls(**lists, config=BodySchemeConfig(**learner), **plain)

    @classmethod
    def from_yaml(cls, path, node_name="scheme_node"):
        """Read a ROS parameter file (``/**:`` or ``<node>:``, then ``ros__parameters:``; nested ``learner:``)."""
        try:
            document = yaml.safe_load(pathlib.Path(path).read_text())
            key = next(k for k in ("/**", node_name, f"/{node_name}") if k in document)
            parameters = document[key]["ros__parameters"]
        except (OSError, yaml.YAMLError, KeyError, TypeError, StopIteration) as error:
            raise InvalidInputError(f"{path}: not a parameter file with /** (or {node_name}) and ros__parameters "
                                    f"({type(error).__name__}: {error})") from error
        flat = {}
        for key, value in parameters.items():
            if isinstance(value, dict):
                flat.update({f"{key}.{sub}": v for sub, v in value.items()})
            else:
                flat[key] = value
        return cls.from_parameters(flat)

    @property
    def state_directory(self):
        """Where ``~/save`` and ``~/load`` names live: ``state_dir``, else the checkpoint's directory, else
        ``$ROS_HOME/body_scheme`` (``~/.ros/body_scheme``)."""
        if self.state_dir:
            return pathlib.Path(self.state_dir).expanduser()
        if self.checkpoint_path:
            return pathlib.Path(self.checkpoint_path).expanduser().resolve().parent
        return pathlib.Path(os.environ.get("ROS_HOME", "~/.ros")).expanduser() / "body_scheme"

    def new_learner(self):
        """A fresh learner: engineered start if ``urdf_path`` is set, else bootstrapping from scratch."""
        initial = engineered_body_scheme(self.urdf_path, self.markers_path, self.joint_names, self.part_ids,
                                         self.urdf_tolerance) if self.urdf_path else None
        return BodySchemeLearner(list(self.part_ids), len(self.joint_names), self.config, initial_models=initial,
                                 action_lower=list(self.action_lower), action_upper=list(self.action_upper))

    @property
    def urdf_tolerance(self):
        """``(urdf_tolerance_trans, urdf_tolerance_rot)``."""
        return (self.urdf_tolerance_trans, self.urdf_tolerance_rot)

    @property
    def message_limits(self):
        """The size limits of one input message (:class:`~body_scheme_nodes.message_feed.MessageLimits`)."""
        return MessageLimits(self.max_message_bytes, self.max_joint_names, self.max_markers)

    def new_pairer(self):
        """The command/observation pairer of these settings."""
        return CommandObservationPairer(settle_time=self.settle_time, max_delay=self.max_delay,
                                        grace=self.pairing_grace)


def specification_tree(urdf_path, markers_path, joint_names, part_ids):
    """The robot's specification: its URDF with its marker file, actions in ``joint_names`` order.

    Raises
    ------
    InvalidInputError
        If the marker file is missing, or the robot's markers are not exactly ``part_ids``.
    """
    if not markers_path:
        raise InvalidInputError("urdf_path needs markers_path: the marker placement file of the robot")
    tree = KinematicTree.from_urdf(pathlib.Path(urdf_path).read_bytes(), markers=load_markers_yaml(markers_path),
                                   joint_actions={name: k for k, name in enumerate(joint_names)})
    if sorted(tree.marker_ids) != sorted(part_ids):
        raise InvalidInputError(f"markers of {markers_path} are {sorted(tree.marker_ids)}, part_ids are "
                                f"{list(part_ids)}")
    return tree


def engineered_body_scheme(urdf_path, markers_path, joint_names, part_ids, tolerance=None):
    """Engineered local models of a robot description, one per edge of its marker tree (the initial body scheme);
    with ``tolerance`` (m, rad; not both 0) an edge over several joints is the specification's chain, calibrated
    from there (:func:`~body_scheme_core.models.engineered.engineered_models`)."""
    tree = specification_tree(urdf_path, markers_path, joint_names, part_ids)
    return engineered_models(tree, tolerance if tolerance is not None and any(tolerance) else None)


def robot_parameter_file(template, tree, robot, sigma_trans=0.01, sigma_rot=0.087):
    """scheme_node's parameter file for ``tree`` (a :class:`KinematicTree` with its markers), learning from scratch:
    ``template`` (the shipped ``config/scheme_node.yaml``, every comment kept) with the robot's part ids, joint names
    and limits and the tracker's noise priors (default 10 mm / 5 deg: a 1280 x 960 camera, 8 cm markers at 2 m).
    ``robot`` names the robot in the header."""

    def flow(values):
        return yaml.safe_dump(list(values), default_flow_style=True, width=10_000).strip()

    values = {"    part_ids": flow(int(i) for i in tree.marker_ids),
              "    joint_names": flow(str(name) for name in tree.action_joint_names),
              "    action_lower": flow(float(v) for v in tree.action_lower),
              "    action_upper": flow(float(v) for v in tree.action_upper),
              "      sigma_trans": repr(float(sigma_trans)), "      sigma_rot": repr(float(sigma_rot))}
    lines, found = [], set()
    for line in template.splitlines():
        if line.startswith("# The robot part is for"):
            line = f"# Written for {robot} by body_scheme_apps (plan_markers, calibrate --simulate): check the limits."
        key = next((k for k in values if line.startswith(k + ":") and k not in found), None)
        if key is not None:
            comment = line.find(" #", len(key) + 1)
            line = f"{key}: {values[key]}" + ("   " + line[comment + 1:] if comment >= 0 else "")
            found.add(key)
        lines.append(line)
    missing = sorted(k.strip() for k in set(values) - found)
    if missing:
        raise InvalidInputError(f"the parameter template has no line for {missing}")
    return "\n".join(lines) + "\n"
