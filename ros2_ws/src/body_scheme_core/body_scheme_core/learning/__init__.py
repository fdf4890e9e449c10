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
- the learner that runs them step by step (:mod:`.learner`): its state, every field once (:mod:`.learner_state`),
  its time step (:mod:`.learner_step`) and joint-fit steps (:mod:`.learner_fit`) as functions of that state, its
  configuration (:mod:`.config`) and input checks (:mod:`.inputs`), and its saved state (:mod:`.state_file`,
  :mod:`.persistence`).

The package exports what users and the other packages call: the learner, its configuration, its saved state, and
the registrations a calibration without a learner needs (a root from points, a chain from the URDF), and the
candidate local models of the paper's fully connected network. Everything else
is imported from the module that defines it (a test imports the module it tests).
"""

from __future__ import annotations

from .chain_refit import register_chain
from .chain_search import same_chain
from .config import BodySchemeConfig
from .learner import BodySchemeLearner
from .persistence import STATE_FORMAT, encode_state, load_state, save_state, write_state_text
from .root_pose import MIN_SPREAD, RootPoseEstimator, point_spread, register_points
from .structure import enumerate_candidates

__all__ = [
    "BodySchemeLearner",
    "BodySchemeConfig",
    "STATE_FORMAT",
    "load_state",
    "save_state",
    "encode_state",
    "write_state_text",
    "RootPoseEstimator",
    "register_points",
    "point_spread",
    "MIN_SPREAD",
    "register_chain",
    "same_chain",
    "enumerate_candidates",
]
