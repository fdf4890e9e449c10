"""The world the body scheme is learnt in, without ROS or pybullet: one kinematic-tree model of a robot and its
markers, URDF and marker files in and out, the synthetic robots, the true body and its faults, observation noise,
motor babbling, babbling sessions and the paper's protocols.

=====================  ====================================================================================
module                 holds
=====================  ====================================================================================
:mod:`.tree`           ``Joint``, ``Marker``, ``KinematicTree``: a robot's specification, forward kinematics
:mod:`.robot_files`    URDF in and out, marker placement YAML
:mod:`.robots`         the synthetic robots (``planar_2dof``, ``arm_4dof``, ``powercube_6dof``, ...)
:mod:`.body`           ``Body`` (commands -> executed joints -> true poses) and the faults that change it
:mod:`.faults`         ``Fault`` at a step, ``REPAIR``, the paper's protocols' fault schedules
:mod:`.noise`          the paper's marker noise and ``ObservationModel``
:mod:`.babbling`       ``babble``: random commands within the joint limits
:mod:`.sessions`       ``Session``, ``make_session`` and the paper's two adaptation protocols
:mod:`.truth`          the true body scheme of a robot: which learned models and trees are right
=====================  ====================================================================================

The pybullet simulator (``body_scheme_sim``) is a rendering and physics backend of this world: it builds its robot
from a ``KinematicTree``, applies the same faults to the same ``Body`` and records the same protocols.
"""

from .babbling import babble
from .body import Body, block_joint, deform_limb, displace_marker
from .faults import (
    FAULT_KINDS,
    PROTOCOL_FAULTS,
    RANDOM_FAULTS,
    REPAIR,
    Fault,
    delta_from_vector,
    parse_fault,
    parse_fault_schedule,
    protocol_schedule,
    random_fault,
)
from .joints import JOINT_TYPES, MOVABLE_JOINT_TYPES, Joint, Marker
from .noise import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS, ObservationModel
from .robot_files import load_markers_yaml, markers_to_yaml, resolve_meshes, tree_from_urdf, tree_to_urdf
from .robots import (
    arm_4dof,
    arm_7dof,
    branching_tree,
    default_world2root,
    planar_2dof,
    powercube_6dof,
    random_tree,
    upper_body,
    zoo_robot,
)
from .sessions import (
    DEFAULT_PERIOD,
    FRAME_ID,
    IMAGE_DELAY_NS,
    START_STAMP_NS,
    Session,
    joint_blocked_protocol,
    limb_deformed_protocol,
    make_session,
)
from .tree import KinematicTree
from .truth import is_correct_model, is_true_tree, least_actions, wrong_models

__all__ = [
    "JOINT_TYPES", "MOVABLE_JOINT_TYPES", "Joint", "Marker", "KinematicTree",
    "tree_from_urdf", "tree_to_urdf", "load_markers_yaml", "markers_to_yaml", "resolve_meshes",
    "planar_2dof", "arm_4dof", "powercube_6dof", "arm_7dof", "upper_body", "branching_tree", "random_tree",
    "zoo_robot", "default_world2root",
    "Body", "block_joint", "deform_limb", "displace_marker",
    "Fault", "REPAIR", "FAULT_KINDS", "parse_fault", "parse_fault_schedule", "delta_from_vector", "PROTOCOL_FAULTS",
    "protocol_schedule", "RANDOM_FAULTS", "random_fault",
    "PAPER_SIGMA_TRANS", "PAPER_SIGMA_ROT", "ObservationModel",
    "babble", "Session", "make_session", "joint_blocked_protocol", "limb_deformed_protocol", "START_STAMP_NS",
    "IMAGE_DELAY_NS", "DEFAULT_PERIOD", "FRAME_ID", "is_correct_model", "is_true_tree", "least_actions", "wrong_models",
]
