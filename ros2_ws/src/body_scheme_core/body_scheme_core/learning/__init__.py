"""Learning and lifelong adaptation of the body scheme (paper Sec. III-A to III-C and III-E).

- relative observations of part pairs (:mod:`.relative`, Sec. III-A);
- the pool of candidate local models, their prequential evaluation and validity (:mod:`.pool`, :mod:`.tracked`,
  :mod:`.validity`, :mod:`.quality`; Eq. 4-7);
- structure search: the minimum spanning tree over the valid models, layer by layer (:mod:`.structure`,
  :mod:`.bootstrap`; Sec. III-C);
- adaptation (:mod:`.adaptation`; Sec. III-E, Eq. 11): change detection (:mod:`.detection`), the search for
  replacements (:mod:`.repair`), GP challengers of rigid joints (:mod:`.challengers`) and the memory of earlier models
  (:mod:`.memory`);
- the root pose and the chain-consistent targets the tree's models are tested against (:mod:`.root_pose`,
  :mod:`.chain`);
- the learner that runs them step by step (:mod:`.learner`, its joint-fit steps in :mod:`.learner_fit`), its
  configuration (:mod:`.config`) and input checks (:mod:`.inputs`), and its saved state (:mod:`.learner_state`,
  :mod:`.persistence`).
"""

from __future__ import annotations

from .adaptation import Adaptation
from .bootstrap import SUSPECT_RATIO, Bootstrap
from .chain import ChainTargets
from .chain_search import identify_chain, register_chain, same_chain
from .challengers import Challengers
from .config import BodySchemeConfig
from .detection import Detection, Mismatch, upstream_edges
from .inputs import (
    MAX_ACTION,
    MAX_ACTIONS,
    MAX_CANDIDATES,
    MAX_PARTS,
    OBSERVATION_TOLERANCE,
    Rejection,
    check_action_bounds,
    check_action_vector,
    check_body_size,
    check_config,
    check_initial_models,
    check_n_actions,
    check_observation_mapping,
    check_part_ids,
    check_stamp,
    filter_observations,
    mirrored_observations,
    rigidity_problem,
    root_part,
)
from .learner import PHASES, BodySchemeLearner
from .learner_fit import JointFitSteps
from .learner_state import (
    STATE_VERSION,
    Calibrated,
    learner_from_state,
    learner_to_state,
    restore,
    snapshot,
    structural_problems,
)
from .memory import Memory, least_recently_used
from .persistence import STATE_FILE_VERSION, STATE_FORMAT, encode_state, load_state, save_state, write_state_text
from .pool import LearningSlots, ModelPool, Targets, check_monitor_settings
from .quality import (
    CLASS_RANKS,
    N_RANKS,
    RANK_PENALTY,
    class_rank,
    model_cost,
    nests,
    prediction_errors,
    relative_complexity,
    replacement_cost,
)
from .relative import PartPairs, RelativeObservations
from .repair import Change, Repair, Replacement, bridge_relative_complexity, tree_halves
from .root_pose import (
    MIN_SPREAD,
    OFFSET_SAMPLES,
    OUTLIER_SIGMAS,
    RootPoseEstimator,
    RootWatch,
    point_spread,
    register_points,
    still_part,
)
from .structure import (
    CANDIDATE_KINDS,
    action_subsets,
    enumerate_candidates,
    kinds_for,
    n_candidates,
    replacement_action_sets,
    replacement_candidates,
    select_spanning_tree,
)
from .tracked import CANDIDATE, MEMORY, TREE, Journal, TrackedModel, nested_models
from .validity import RATIO_CLIP, ValidityMonitor, WindowStats, translation_threshold

__all__ = [
    "PartPairs",
    "RelativeObservations",
    "CLASS_RANKS",
    "N_RANKS",
    "RANK_PENALTY",
    "class_rank",
    "nests",
    "prediction_errors",
    "model_cost",
    "relative_complexity",
    "replacement_cost",
    "RATIO_CLIP",
    "translation_threshold",
    "WindowStats",
    "ValidityMonitor",
    "TREE",
    "MEMORY",
    "CANDIDATE",
    "TrackedModel",
    "nested_models",
    "Journal",
    "Targets",
    "LearningSlots",
    "ModelPool",
    "check_monitor_settings",
    "CANDIDATE_KINDS",
    "action_subsets",
    "kinds_for",
    "enumerate_candidates",
    "n_candidates",
    "replacement_action_sets",
    "replacement_candidates",
    "select_spanning_tree",
    "Bootstrap",
    "SUSPECT_RATIO",
    "Detection",
    "Mismatch",
    "upstream_edges",
    "Repair",
    "Change",
    "Replacement",
    "tree_halves",
    "bridge_relative_complexity",
    "Challengers",
    "Memory",
    "least_recently_used",
    "Adaptation",
    "ChainTargets",
    "identify_chain",
    "register_chain",
    "same_chain",
    "still_part",
    "RootPoseEstimator",
    "RootWatch",
    "register_points",
    "point_spread",
    "MIN_SPREAD",
    "OUTLIER_SIGMAS",
    "OFFSET_SAMPLES",
    "BodySchemeConfig",
    "mirrored_observations",
    "OBSERVATION_TOLERANCE",
    "MAX_ACTION",
    "MAX_PARTS",
    "MAX_ACTIONS",
    "MAX_CANDIDATES",
    "check_body_size",
    "Rejection",
    "check_config",
    "check_part_ids",
    "check_n_actions",
    "root_part",
    "check_action_bounds",
    "check_initial_models",
    "check_action_vector",
    "check_stamp",
    "check_observation_mapping",
    "filter_observations",
    "rigidity_problem",
    "STATE_VERSION",
    "Calibrated",
    "learner_to_state",
    "learner_from_state",
    "snapshot",
    "restore",
    "structural_problems",
    "JointFitSteps",
    "BodySchemeLearner",
    "PHASES",
    "save_state",
    "encode_state",
    "write_state_text",
    "load_state",
    "STATE_FORMAT",
    "STATE_FILE_VERSION",
]
