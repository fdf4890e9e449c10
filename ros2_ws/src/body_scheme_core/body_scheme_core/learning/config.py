"""Configuration of the body-scheme learner: one validated dataclass, the single source of defaults.

The ROS nodes declare one parameter per field (same name) and build this object from them; the YAML files in
``body_scheme_nodes/config`` mirror these defaults. The defaults of the marker noise and of the GP hyperparameters are
those of the models (:mod:`~body_scheme_core.models.gp_kernel`), which do not depend on this module.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..errors import InvalidInputError
from ..limits import MAX_CHAIN_JOINTS, MAX_NOISE, MAX_WINDOW
from ..models import (
    DEFAULT_LENGTH_SCALE,
    DEFAULT_SIGMA_ROT,
    DEFAULT_SIGMA_TRANS,
    DEFAULT_SIGNAL_STD_ROT,
    DEFAULT_SIGNAL_STD_TRANS,
)
from .structure import CANDIDATE_KINDS

__all__ = ["BodySchemeConfig"]

#: Bounds of the integer settings. The upper ones are far beyond any use and keep a setting from allocating the
#: machine's memory or overflowing a step count.
_INTEGERS = {"test_window": (1, MAX_WINDOW), "train_window": (1, MAX_WINDOW), "min_test_samples": (1, MAX_WINDOW),
             "max_complexity": (0, 100), "bootstrap_patience": (1, 10**6), "reinstate_min_samples": (1, MAX_WINDOW),
             "memory_size": (0, 1000), "history_length": (1, 10**5), "calibration_period": (1, 10**6),
             "replacement_max_relative": (0, 100), "replacement_patience": (1, 10**6), "bridge_patience": (1, 10**6),
             "root_window": (1, 10**5), "race_samples": (0, MAX_WINDOW), "race_min_train": (1, MAX_WINDOW),
             "max_chain_joints": (0, MAX_CHAIN_JOINTS)}
#: Bounds of the number settings (all must be finite; the lower bound is exclusive where it is 0 and the setting
#: divides or scales).
_NUMBERS = {"validity_sigmas": (0.0, 100.0), "gp_length_scale": (0.0, 1e3), "gp_signal_std_trans": (0.0, 1e3),
            "gp_signal_std_rot": (0.0, 1e3), "f_scale": (0.0, 1e3), "stale_fraction": (None, 1.0),
            "cusum_drift": (0.0, 1e6), "cusum_threshold": (0.0, 1e6), "cusum_clip": (0.0, 1e6),
            "dominance_margin": (0.0, 1e3), "challenge_margin": (0.0, 1e3), "max_distance": (0.0, 1e4),
            "workspace_margin": (0.0, 1e4), "action_margin": (None, 1e3), "consistency_alpha": (0.0, 1.0),
            "race_ratio": (0.0, 1e3)}


@dataclass(frozen=True)
class BodySchemeConfig:
    """Hyperparameters of learning, structure search, change detection and control.

    Attributes
    ----------
    sigma_trans : float or "auto"
        Prior of the observation noise of one marker's position as the RMS of its 3D error, in m (the paper's "44 mm
        in 3D space"; per axis ``sigma_trans / sqrt(3)``). The learner estimates the noise from the joint fit's
        residuals (:mod:`~body_scheme_core.calibration.noise_model`: per marker, across and along the camera's ray); a
        number is where it starts and weighs like 50 observations, ``"auto"`` (default) starts from 50 mm and yields to
        the first estimate.
    sigma_rot : float or "auto"
        The same for the orientation: the RMS of the rotation-vector error, in rad (``"auto"``: 15 deg).
    theta_trans, theta_rot : float or None
        Validity thresholds on the mean translational (m) and rotational (rad) prediction error over the test
        window (paper Eq. 5-6). ``None`` (default) means ``validity_sigmas`` times the current noise estimate: 3 sigma
        as in the paper. A number fixes the threshold.
    validity_sigmas : float
        Multiple of sigma used when a threshold is ``None``.
    test_window : int
        ``|D_test|``: number of latest samples a local model's prediction error is averaged over.
    train_window : int
        ``|D_train|``: number of samples a candidate local model is trained on after it is instantiated; then it is
        frozen. The models of the body scheme keep learning from every observation through the joint fit.
    candidate_kinds : tuple of str
        Local-model classes instantiated as candidates (bootstrapping and replacements): any of ``"static"``,
        ``"prismatic"``, ``"revolute"``, ``"gp"``. ``("gp",)`` is the paper's learner.
    fit_joint_scale : bool
        Whether rigid joint models fit the scale between an action and the joint's motion (rad or m per action
        unit). False (default): actions are joint positions (rad, m), as in the paper, and the models assume it: one
        parameter fewer per joint and better accuracy from few samples. Set True when commands are in other units.
    max_complexity : int
        Largest number of actions a local model may depend on (number of complexity layers searched - 1).
    min_test_samples : int
        A model needs at least this many test samples before its validity is judged.
    root : int or None
        Part id of the root of the body scheme (the robot's trunk). ``None``: the lowest known part id.
    gp_length_scale : float
        Length scale of the squared-exponential kernel over actions, in rad.
    gp_signal_std_trans, gp_signal_std_rot : float
        Prior standard deviation of the translational (m) and rotation-matrix components around the training mean.
    gp_optimize : bool
        GP edges of the body scheme, refitted by the joint fit, choose their length scale and noise ratio by
        marginal likelihood; candidates keep the fixed ``gp_length_scale`` and the noise ratio of the sigmas (one
        factorisation for hundreds of them).
    stale_fraction : float
        While a model is still learning (n training samples), errors of its predictions made with fewer than
        ``floor(stale_fraction * n)`` samples are ignored when judging its validity (0 disables the rule).
    bootstrap_patience : int
        Bootstrapping also ends when the valid spanning tree's models are frozen and the tree has not changed for
        this many steps, even if candidates of pairs rarely seen together are still learning.
    cusum_drift, cusum_threshold, cusum_clip : float
        One-sided CUSUM per channel (position, orientation) on a body-scheme model's squared per-sample error in units
        of its noise (``(validity_sigmas e / theta)^2``, mean 1 while the model is right): reference value k, alarm
        level h, and the clip applied to each sample first (outlier robustness).
    dominance_margin : float
        A candidate is not eligible for the spanning tree while a candidate of the same pair whose actions include
        its own predicts the same test samples better by more than this many thresholds (mean of ``e / theta``, in
        either channel): the extra actions clearly matter, so the simpler model is biased even if it is valid.
    challenge_margin : float
        While a body-scheme model's CUSUM is above zero, a remembered model of the same pair takes over at once
        when, over the samples since the CUSUM left zero, it is valid and beats the current model in both channels
        by more than this many thresholds on average (paired comparison).
    reinstate_min_samples : int
        A remembered model is put back when its mean errors over at least this many samples since the estimated
        change point are below the validity thresholds.
    memory_size : int
        Retired models remembered per pair of parts (least recently used dropped first); 0 disables memory.
    history_length : int
        Raw steps (actions and observations) kept: the window of the joint fit of the body scheme, and what is
        replayed to replacement models from the change point on.
    calibration_period : int
        Largest number of steps between joint fits of the body scheme (root pose and every tree model against the
        absolute observations of the history). A fit runs at once after every change of the tree, and once the
        observations usable by the newest edge grew by a tenth since the last fit (so every step early on and right
        after a change).
    f_scale : float
        Huber threshold of the robust loss of the rigid-joint fits and the joint fit, in sigmas of one residual
        component.
    replacement_max_relative : int
        Replacements are sampled for every action set whose relative complexity (size of the symmetric
        difference with the failed model's actions, paper Eq. 11) is at most this.
    replacement_patience : int
        If no replacement of a mismatching model is valid this many steps after sampling, new ones are sampled
        from the most recent ``test_window`` steps of the history.
    bridge_patience : int
        If no replacement of the failed pair is valid this many steps after sampling, candidates of every other
        pair that reconnects the two halves of the tree are sampled too (a local re-bootstrap), so that a wrong edge
        can be replaced by a right one.
    root_window : int
        Number of recent root observations whose robust mean (coordinate-wise median) gives the root pose in the
        world for :meth:`BodySchemeLearner.predict`.
    max_distance : float
        Plausibility gate, m: an observed pose farther than this from the camera is rejected (counted as
        ``out_of_workspace``) instead of learnt from. The default suits a table-top arm seen from a few metres.
    workspace_margin : float
        Plausibility gate derived from the robot, m: once the body scheme is calibrated, an observed pose farther
        from the root part than the robot's learned reach (the largest root-to-part distance the calibrated scheme
        predicts over the history's actions) plus this margin is rejected as ``out_of_workspace``. Faults (a bent
        limb, a tool) move parts by less than this; a 5 m outlier is refused. Finite: a large margin (100 m)
        turns the gate off in effect.
    action_margin : float
        Plausibility gate on commands, as a fraction of each joint's range: actions beyond the joint limits by more
        than this are refused (``update`` raises ``InvalidInputError``).
    consistency_alpha : float
        Significance of the lack-of-fit test after every joint fit (:mod:`~body_scheme_core.calibration.consistency`),
        for all parts together (Bonferroni): a part whose residuals depend on the commands at this level is not
        explained by the body scheme, which is then not trusted and searched again.
    lazy_layers : bool
        Bootstrapping starts with the candidates of complexity <= 1 and instantiates layer ``k + 1`` only for the
        pairs across the parts that layers <= k cannot connect (paper Sec. III-D), trained at once from the history.
        Off by default (every layer up to ``max_complexity`` from the start). With racing 3.5-4.5x faster on big
        bodies, but racing loses true trees on the robot zoo; alone, lazy layers are as good as eager up to the paper's
        noise and worse at the harsh level (docs/core/learning-and-adaptation.md, Sec. 4).
    race_samples, race_ratio, race_min_train : int, float, int
        Racing while bootstrapping: a candidate whose last ``race_samples`` errors all exceed ``race_ratio`` times
        the validity threshold, each predicted after at least ``race_min_train`` training samples, is dropped
        (:meth:`~body_scheme_core.learning.validity.ValidityMonitor.hopeless`; counted in ``raced``). 0 (the default):
        no racing; 3 with lazy layers is what the bootstrap bench measures.
    max_chain_joints : int
        Parts that no layer up to ``max_complexity`` connects (a tool observed past six joints) are connected by a
        chain of at most this many joints, identified from the samples in which few actions moved
        (:mod:`~body_scheme_core.learning.chain_search`), and so are the two parts of an edge that leaves its child
        unexplained while bootstrapping; 0 or 1: no chains (a chain has two joints or more).
    sensor_root : bool
        The root part (``root``, required) is the camera or tracker itself, rigid with the robot's base: its pose is
        the identity at every step, given to the learner whether or not anything observed it, so no base marker is
        needed. Off: the root is a part the camera observes.
    detection_covariances : bool
        Weigh an observation given with its own covariance (``update(..., covariances=...)``; a tag detector's
        ``MarkerPoses`` covariance) by it, times a learned scale, in the joint fit. Off (the default, and for a
        driver whose covariances are constants): every observation is weighed by the learned per-marker noise. On
        helps where each detection's noise is random and its own (the joint fit's effector error 0.55 times as large
        when it varies one to eight times between detections); on the simulator's rendered images, whose errors
        are view-dependent biases the covariance does not describe, it made 2 of 3 sessions worse (docs/nodes.md).
    mirror_hypotheses : bool
        While a candidate learns (bootstrapping), a relative observation may be read with one or both of its poses
        mirrored about the camera's ray (the planar ambiguity a marker tracker falls into,
        :func:`~body_scheme_core.transforms.mirror_about_ray`): where the given reading is off the candidate's
        prediction by more than a threshold and the other is within both and less than half as far, so a flip before
        the scheme is calibrated neither teaches a model nor makes it invalid. Once it is calibrated, a flip off the
        prediction by more than a third of the rotational threshold is taken in mirrored too, or refused where its
        position is off as well (not only one off by more than the threshold:
        :data:`~body_scheme_core.learning.mirrors.EAGER_FLOOR`). Off (the default): poses
        as given, as a laser tracker or motion capture needs. On for a tag tracker whose poses flip often (the robot
        zoo's 30 % level: the true tree in 28 of 40 bodies instead of 15); on flip-free poses at the paper's noise
        (thresholds of 45 deg) the other readings make wrong candidates valid for a while: more tree changes,
        bootstrapping 2.8 times as long on the 6-DOF arm (docs/core/learning-and-adaptation.md, Sec. 1).
    """

    sigma_trans: float | str = "auto"
    sigma_rot: float | str = "auto"
    theta_trans: float | None = None
    theta_rot: float | None = None
    validity_sigmas: float = 3.0
    test_window: int = 15
    train_window: int = 30
    candidate_kinds: tuple = ("static", "prismatic", "revolute", "gp")
    fit_joint_scale: bool = False
    max_complexity: int = 2
    min_test_samples: int = 3
    root: int | None = None
    gp_length_scale: float = DEFAULT_LENGTH_SCALE
    gp_signal_std_trans: float = DEFAULT_SIGNAL_STD_TRANS
    gp_signal_std_rot: float = DEFAULT_SIGNAL_STD_ROT
    gp_optimize: bool = True
    stale_fraction: float = 0.5
    bootstrap_patience: int = 30
    cusum_drift: float = 1.5
    cusum_threshold: float = 12.0
    cusum_clip: float = 6.0
    dominance_margin: float = 0.15
    challenge_margin: float = 0.25
    reinstate_min_samples: int = 2
    memory_size: int = 4
    history_length: int = 200
    calibration_period: int = 100
    f_scale: float = 3.0
    replacement_max_relative: int = 2
    replacement_patience: int = 60
    bridge_patience: int = 15
    root_window: int = 50
    max_distance: float = 10.0
    workspace_margin: float = 0.5
    action_margin: float = 0.05
    consistency_alpha: float = 1e-3
    lazy_layers: bool = False
    race_samples: int = 0
    race_ratio: float = 2.0
    race_min_train: int = 5
    max_chain_joints: int = MAX_CHAIN_JOINTS
    sensor_root: bool = False
    detection_covariances: bool = False
    mirror_hypotheses: bool = False

    def __post_init__(self):
        for name in ("sigma_trans", "sigma_rot"):
            if getattr(self, name) != "auto":
                _check_number(name, getattr(self, name), 0.0, MAX_NOISE, '"auto" or ')
        for name in ("theta_trans", "theta_rot"):
            if getattr(self, name) is not None:
                _check_number(name, getattr(self, name), 0.0, MAX_NOISE, "null or ")
        for name, (low, high) in _INTEGERS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise InvalidInputError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
        for name, (low, high) in _NUMBERS.items():
            _check_number(name, getattr(self, name), low, high)
        for name in ("stale_fraction", "consistency_alpha"):
            if not getattr(self, name) < 1.0:
                raise InvalidInputError(f"{name} must be below 1, got {getattr(self, name)!r}")
        if not self.cusum_clip > self.cusum_drift:
            raise InvalidInputError(f"cusum_clip ({self.cusum_clip!r}) must exceed cusum_drift ({self.cusum_drift!r})")
        for name in ("fit_joint_scale", "gp_optimize", "lazy_layers", "sensor_root", "detection_covariances",
                     "mirror_hypotheses"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidInputError(f"{name} must be true or false, got {getattr(self, name)!r}")
        kinds = self.candidate_kinds
        if isinstance(kinds, str) or not isinstance(kinds, (tuple, list)):
            raise InvalidInputError(f"candidate_kinds must be a list of model classes, got {kinds!r}")
        kinds = tuple(kinds)
        if not kinds or len(set(kinds)) != len(kinds) or any(k not in CANDIDATE_KINDS for k in kinds):
            raise InvalidInputError(f"candidate_kinds must be distinct classes of {list(CANDIDATE_KINDS)}, got "
                                    f"{list(kinds)}")
        object.__setattr__(self, "candidate_kinds", kinds)
        if self.min_test_samples > self.test_window:
            raise InvalidInputError(
                f"min_test_samples ({self.min_test_samples}) must not exceed test_window ({self.test_window})")
        if self.root is not None and (isinstance(self.root, bool) or not isinstance(self.root, int)):
            raise InvalidInputError(f"root must be a part id or null, got {self.root!r}")
        if self.sensor_root and self.root is None:
            raise InvalidInputError("sensor_root needs root: the part id that stands for the camera or tracker")

    @property
    def prior_sigma_trans(self):
        """The noise prior's 3D RMS position error (m): ``sigma_trans``, or the default of ``"auto"``."""
        return DEFAULT_SIGMA_TRANS if self.sigma_trans == "auto" else float(self.sigma_trans)

    @property
    def prior_sigma_rot(self):
        """The noise prior's 3D RMS orientation error (rad)."""
        return DEFAULT_SIGMA_ROT if self.sigma_rot == "auto" else float(self.sigma_rot)

    def to_dict(self):
        """Plain dict of all fields (JSON-serialisable; tuples as lists)."""
        data = dataclasses.asdict(self)
        data["candidate_kinds"] = list(self.candidate_kinds)
        return data

    @classmethod
    def from_dict(cls, data):
        """Build from a dict, rejecting unknown keys with the list of known ones."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise InvalidInputError(f"unknown configuration key(s) {unknown}; known: {sorted(known)}")
        return cls(**data)


def _check_number(name, value, low, high, alternative=""):
    """Raise unless ``value`` is a finite number in ``(low, high]`` (``low`` None: ``[0, high]``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not (
            (value >= 0.0 if low is None else value > low) and value <= high):
        bound = f"in [0, {high}]" if low is None else f"in ({low}, {high}]"
        raise InvalidInputError(f"{name} must be {alternative}a finite number {bound}, got {value!r}")
