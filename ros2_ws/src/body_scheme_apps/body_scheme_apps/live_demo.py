"""``live_demo``: the whole node suite as a live ROS graph, with a scripted joint block and repair.

sim_node (babbling, rendered camera, scheduled faults) -> tracker_node (ArUco) -> scheme_node (learns the body scheme
from scratch, detects the fault, adapts) -> control_node (IK on the learned scheme), each its own process talking over
DDS. A monitor node records what a user would watch (events, structure, ``/diagnostics``, predictions against ground
truth), then, once babbling ends, sends IK targets and measures where the simulated end effector really goes.
It prints the event timeline and a summary, and writes ``summary.json`` and ``live_demo.png`` to the output directory,
and records the whole session as a rosbag2 (mcap) in ``<out>/session`` (:data:`RECORDED_TOPICS`; open it in Foxglove
with ``ros2_ws/src/body_scheme_nodes/config/body_scheme.foxglove.json``).

``make demo`` runs ``python -m body_scheme_apps.live_demo`` (also ``ros2 run body_scheme_apps live_demo``); without
the ``launch`` package it starts the installed node executables as processes (``body_scheme_nodes.graph``).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from body_scheme_core.errors import BodySchemeError
from body_scheme_core.transforms import translational_error
from body_scheme_core.world import PAPER_SIGMA_ROT, PAPER_SIGMA_TRANS
from body_scheme_msgs.msg import BodySchemeStructure, IKResult, IKTarget, MarkerPoses, ModelSnapshot, SchemeEvent
from body_scheme_nodes import conversions
from body_scheme_nodes.graph import NodeProcess, monitor_node, spin_until
from body_scheme_nodes.qos import LATCHED, RECENT_EVENTS
from body_scheme_nodes.recorder import GraphRecorder
from body_scheme_sim.camera import camera_parameters
from body_scheme_sim.robots import ROBOT_BUILDERS, load_robot, robot_files
from body_scheme_sim.sessions import RENDERED_SIGMA_ROT, RENDERED_SIGMA_TRANS

from .entry import command
from .robot_option import add_robot_arguments, resolve_robot

__all__ = ["DemoResult", "RECORDED_TOPICS", "run_live_demo", "main"]

#: (topic, type, latched or QoS profile) of the session recording: commands, observations, predictions, structure,
#: events, diagnostics, the view (markers, poses, tf, learned URDF), IK and the simulator's ground truth. Camera images
#: are left out (megabytes per second).
RECORDED_TOPICS = (
    ("joint_commands", JointState, False), ("observations", MarkerPoses, False),
    ("predicted_poses", MarkerPoses, False), ("ground_truth/marker_poses", MarkerPoses, False),
    ("body_scheme/structure", BodySchemeStructure, True), ("body_scheme/snapshot", ModelSnapshot, True),
    ("body_scheme/events", SchemeEvent, RECENT_EVENTS), ("/diagnostics", DiagnosticArray, False),
    ("body_scheme/markers", MarkerArray, False), ("body_scheme/poses", PoseArray, False), ("/tf", TFMessage, False),
    ("body_scheme/robot_description", String, True), ("ik_target", IKTarget, False), ("ik_result", IKResult, False),
)

_LEVELS = {DiagnosticStatus.OK: "OK", DiagnosticStatus.WARN: "WARN", DiagnosticStatus.ERROR: "ERROR",
           DiagnosticStatus.STALE: "STALE"}


@dataclass
class DemoResult:
    """What the live demo observed. Steps are indices of executed sim commands (the ground-truth messages)."""

    steps: int
    faults: list
    perception: str
    true_edges: list
    learned_edges: list = field(default_factory=list)
    events: list = field(default_factory=list)          # dicts: step, kind, model, reason
    diagnostics: list = field(default_factory=list)   # (step, level) of "/scheme_node: body scheme" whenever it changes
    prediction_error: list = field(default_factory=list)  # (step, end-effector prediction error in m)
    ik: list = field(default_factory=list)  # dicts: target, success, reason, residual, position_std, reached_error
    scheme_status: dict = field(default_factory=dict)  # last "/scheme_node: body scheme" key-values, parsed
    n_observations: int = 0
    wall_time_s: float = 0.0
    rates: dict = field(default_factory=dict)
    recorded: dict = field(default_factory=dict)      # topic -> messages in <out>/session (the mcap recording)

    def structure_learned(self):
        """Whether the final structure is the robot's true marker tree."""
        return {frozenset(e) for e in self.learned_edges} == {frozenset(e) for e in self.true_edges}


class _Monitor:
    """The demo's own rclpy node: subscribes to everything a user would watch and sends IK targets."""

    def __init__(self, node, end_effector, controller=False):
        self.node = node
        self.end_effector = end_effector
        # Through a controller sim_node takes a picture every camera_period at rest: the command's ground truth is
        # the first one after its action signal (babble_node's or control_node's joint_commands).
        self.controller = controller
        self.actions = []          # stamps of the action signals not yet shown
        node.create_subscription(JointState, "joint_commands", self._action, 100)
        self.truth = []            # (stamp, {id: camera2marker}) in arrival order = command order
        self.step_of_stamp = {}
        self.predicted = {}        # stamp -> camera2marker of the end effector
        self.events, self.ik_results, self.diagnostics = [], [], []
        self.structure = None
        self.scheme_status = {}
        self.n_observations = 0
        self.seen = {}             # stamp -> ids observed (tracker or noise model)
        node.create_subscription(MarkerPoses, "ground_truth/marker_poses", self._truth, 100)
        node.create_subscription(MarkerPoses, "predicted_poses", self._predicted, 100)
        node.create_subscription(MarkerPoses, "observations", self._observation, 100)
        node.create_subscription(SchemeEvent, "body_scheme/events", self.events.append, RECENT_EVENTS)  # none missed
        node.create_subscription(BodySchemeStructure, "body_scheme/structure", self._structure, LATCHED)
        node.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 10)
        node.create_subscription(IKResult, "ik_result", self.ik_results.append, 10)
        self.targets = node.create_publisher(IKTarget, "ik_target", 10)

    def _action(self, msg):
        if self.controller:
            self.actions.append(conversions.seconds_from_stamp(msg.header.stamp))

    def _truth(self, msg):
        stamp, poses, _ = conversions.observations_from_msg(msg)
        if self.controller:
            shown = [a for a in self.actions if a <= stamp]
            if not shown:
                return  # a picture of a command already shown, or of none yet
            self.actions = [a for a in self.actions if a > stamp]
        self.step_of_stamp[stamp] = len(self.truth)
        self.truth.append((stamp, poses))

    def _predicted(self, msg):
        stamp, poses, _ = conversions.observations_from_msg(msg)
        if self.end_effector in poses:
            self.predicted[stamp] = poses[self.end_effector]

    def _observation(self, msg):
        self.n_observations += 1
        stamp, poses, _ = conversions.observations_from_msg(msg)
        self.seen[stamp] = set(poses)

    def _structure(self, msg):
        self.structure = msg

    def _diagnostics(self, msg):
        for status in msg.status:
            if status.name == "/scheme_node: body scheme":
                self.scheme_status = {kv.key: _number(kv.value) for kv in status.values}
                level = _LEVELS.get(status.level, str(status.level))
                if not self.diagnostics or self.diagnostics[-1][1] != level:
                    self.diagnostics.append((len(self.truth), level, status.message))

    def step(self, stamp):
        """Command index of a sample stamp (the ground truth carries the same stamp as the image)."""
        return self.step_of_stamp.get(stamp, -1)


def domain_id(env=None):
    """The ROS domain id of the node processes: ``env``'s ``ROS_DOMAIN_ID``, else this process's (as the nodes
    inherit it), 0 when unset or empty. The monitor must join the same domain or it never sees the graph."""
    value = (os.environ if env is None else env).get("ROS_DOMAIN_ID", "").strip()
    return int(value) if value else 0


def _number(text):
    """A diagnostics value as int or float when it is one, else the text."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


#: The demo's faults on the shipped 6-DOF arm: its sixth joint (action 5) blocked at 0.8 rad, then repaired.
DEMO_FAULTS = ("120:block_joint:5:0.8", "220:repair")
#: sim_node's ``max_in_flight`` in the demo: twice those in flight on an idle machine (0.3 s latency at 13 commands/s);
#: under load they wait well under scheme_node's ``max_sample_age`` (a bootstrapping step takes 20-60 ms).
DEMO_MAX_IN_FLIGHT = 10


def run_live_demo(out_dir, robot="powercube_6dof", steps=300, period=0.05, faults=None, perception="noise",
                  n_targets=5, seed=0, sigma_trans=None, sigma_rot=None, env=None, log=None, markers_path=None,
                  camera=None, package_path=(), babble="sim"):
    """Start the graph, babble ``steps`` commands with the scheduled ``faults``, then test IK; returns a DemoResult.

    Parameters
    ----------
    out_dir : path-like
        Where node logs, ``summary.json`` and ``live_demo.png`` go.
    robot : str
        Shipped robot name (its marker with the highest id is the end effector).
    steps : int
        Babbled commands before the IK phase.
    period : float
        Seconds between babbled commands.
    faults : sequence of str, optional
        sim_node fault schedule (``"step:kind:args"``, steps count executed commands). Default: :data:`DEMO_FAULTS`
        on the shipped ``powercube_6dof`` (the demo's block is of its sixth joint), none on any other robot.
    perception : {"noise", "rendered"}
        The simulator's noise model straight to scheme_node (the paper's protocol), or rendered images through
        tracker_node.
    sigma_trans, sigma_rot : float or None
        RMS 3D position (m) and orientation (rad) error of a marker: the noise model's (noise perception) and the
        learner's noise sigmas (so its 3-sigma validity thresholds). ``None``: the paper's 44 mm and 15 deg with noise
        perception, :data:`~body_scheme_sim.sessions.RENDERED_SIGMA_TRANS` and ``RENDERED_SIGMA_ROT`` with rendered
        perception.
    n_targets : int
        IK targets: end-effector positions the healthy arm reached while babbling (reachable by construction).
    env : dict, optional
        Environment of the node processes (e.g. ROS_DOMAIN_ID); also applied to this process's rclpy context.
    log : callable, optional
        Called with each progress line (default: printed at once, also into a pipe).
    babble : {"sim", "controller"}
        ``sim``: sim_node babbles by itself every ``period`` (at most: it waits while :data:`DEMO_MAX_IN_FLIGHT`
        pictures are undecided). ``controller``: the graph a real robot uses,
        babble_node -> sim_node as a JointTrajectoryController (moves at 12 rad/s, 100 rad/s^2, each settled before
        the next) -> camera; control_node executes the IK answers through the same interface (``period`` unused).
    markers_path, camera, package_path
        Your robot (:mod:`~body_scheme_apps.robot_option`): its marker file (default: the shipped one or beside the
        URDF), the simulated camera (default: the simulator's), directories for its ``package://`` meshes.
    """
    if perception not in ("noise", "rendered"):
        raise ValueError(f"perception must be 'noise' or 'rendered', got {perception!r}")
    if babble not in ("sim", "controller"):
        raise ValueError(f"babble must be 'sim' or 'controller', got {babble!r}")
    controller = babble == "controller"
    rendered = perception == "rendered"
    log = functools.partial(print, flush=True) if log is None else log
    sigma_trans = (RENDERED_SIGMA_TRANS if rendered else PAPER_SIGMA_TRANS) if sigma_trans is None else sigma_trans
    sigma_rot = (RENDERED_SIGMA_ROT if rendered else PAPER_SIGMA_ROT) if sigma_rot is None else sigma_rot
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    markers_path = robot_files(robot, markers_path)[1]
    tree = load_robot(robot, markers_path)
    shipped = str(robot) in ROBOT_BUILDERS
    ids = [int(i) for i in tree.marker_ids]
    end_effector = max(ids)
    names = list(tree.action_joint_names)
    lower, upper = [float(v) for v in tree.action_lower], [float(v) for v in tree.action_upper]
    if faults is None:
        faults = DEMO_FAULTS if robot == "powercube_6dof" else ()
    result = DemoResult(steps=steps, faults=list(faults), perception=perception,
                        true_edges=[list(e) for e in tree.marker_tree_edges()])

    with monitor_node("live_demo_monitor", domain_id(env)) as (node, executor):
        monitor = _Monitor(node, end_effector, controller)
        shutil.rmtree(out_dir / "session", ignore_errors=True)
        recorder = GraphRecorder(node, out_dir / "session", RECORDED_TOPICS)
        processes = []
        start = time.monotonic()
        try:
            def start_node(package, name, parameters):
                processes.append(NodeProcess(package, name, parameters, out_dir / "logs", env=env))
                log(f"started {package}/{name}")

            # The learner's noise sigmas (and so its 3-sigma validity thresholds) are those of the perception in use.
            learner_noise = {"learner.sigma_trans": float(sigma_trans), "learner.sigma_rot": float(sigma_rot)}
            start_node("body_scheme_nodes", "scheme_node", {
                "part_ids": ids, "joint_names": names, "action_lower": lower, "action_upper": upper, **learner_noise})
            arm = {"robot": str(robot), "package_path": list(package_path), "max_velocity": 12.0,
                   "max_acceleration": 100.0, "settle_window": 0.05}
            start_node("body_scheme_nodes", "control_node", {"part_id": end_effector, "tolerance": 0.05,
                                                             **({"execute": True, **arm} if controller else {})})
            if perception == "rendered":
                start_node("body_scheme_nodes", "tracker_node", {"markers_path": str(markers_path),
                                                                 "image_reliability": "reliable"})
            if not spin_until(executor, lambda: monitor.structure is not None, timeout=60):
                raise RuntimeError("scheme_node did not come up within 60 s; see " + str(out_dir / "logs"))
            # The sim babbles only once scheme_node and control_node subscribe to its commands (messages sent before
            # discovery matched are lost), and the tracker (or scheme_node) and this monitor to its outputs.
            if controller:  # babble_node drives sim_node as a real arm's controller; faults are expected here
                start_node("body_scheme_nodes", "babble_node", {**arm, "steps": steps, "seed": seed, "dwell": 0.05,
                                                                "error_hold": 600.0})
            # A busy machine slows the babbling down instead of shedding the samples the story is told in.
            start_node("body_scheme_nodes", "sim_node", {"wait_for_subscribers": 0 if controller else 2,
                "max_in_flight": 0 if controller else DEMO_MAX_IN_FLIGHT,
                **({} if camera is None else camera_parameters(camera)), "camera_period": 0.05,
                "markers_path": str(markers_path), "package_path": list(package_path),
                "robot": str(robot), "perception_mode": perception, "babbling": not controller,
                "babbling_period": period,
                "babbling_steps": steps, "seed": seed, "fault_schedule": list(faults),
                "sigma_trans": float(sigma_trans), "sigma_rot": float(sigma_rot),
                # The shipped arms keep their last two markers in view (the IK targets'); a robot of yours babbles
                # over its whole range (its planned markers are seen together too rarely for such a screen).
                "markers_of_interest": [end_effector - 1, end_effector] if len(ids) > 2 and shipped else []})

            def alive():
                for process in processes:
                    if not process.running():
                        raise RuntimeError(f"{process.name} exited; its log:\n{process.output()[-3000:]}")

            how = "through the controller interface" if controller else f"{period:.2f} s apart"
            log(f"babbling {steps} commands ({how}) with faults {list(faults)} ...")
            babble_start = time.monotonic()
            # The sim's pace is scheme_node's when it waits for it (max_in_flight): give up after a minute without one.
            if not spin_until(executor, lambda: len(monitor.truth) >= steps, timeout=60, during=alive,
                         progress=lambda: len(monitor.truth)):
                raise RuntimeError(f"only {len(monitor.truth)} of {steps} commands executed (none for 60 s)")
            babble_time = time.monotonic() - babble_start
            spin_until(executor, lambda: False, timeout=1.0)  # let scheme_node drain its queue

            # IK: end-effector positions the arm reached after the last repair, so reachable by the healthy arm.
            last_fault = max([int(f.split(":")[0]) for f in faults] or [0])
            rng = np.random.default_rng(seed)
            # Targets where the camera saw every marker: configurations the learned models had data for (IK stays in
            # their trained range, so a target only reachable where a link was never seen may be refused).
            pool = [k for k in range(last_fault + 5, steps)
                    if monitor.seen.get(monitor.truth[k][0], set()) >= set(ids)] or \
                [k for k in range(last_fault + 5, steps) if end_effector in monitor.truth[k][1]]
            for k in rng.choice(pool, size=min(n_targets, len(pool)), replace=False):
                target = monitor.truth[k][1][end_effector][:3, 3]
                n_results, n_truth = len(monitor.ik_results), len(monitor.truth)
                msg = IKTarget(part_id=end_effector)
                msg.header.frame_id = "camera"
                msg.position.x, msg.position.y, msg.position.z = (float(v) for v in target)
                monitor.targets.publish(msg)
                spin_until(executor, lambda n=n_results: len(monitor.ik_results) > n, timeout=20, during=alive)
                outcome = monitor.ik_results[-1] if len(monitor.ik_results) > n_results else None
                record = {"target": target.tolist(), "success": bool(outcome and outcome.success),
                          "reason": outcome.reason if outcome else "no IKResult within 20 s",
                          "residual": float(outcome.residual) if outcome else float("nan"),
                          "position_std": float(outcome.position_std) if outcome else float("nan"),
                          "reached_error": None}
                if outcome is not None and outcome.success and spin_until(
                        executor, lambda n=n_truth: len(monitor.truth) > n, timeout=10, during=alive):
                    reached = monitor.truth[-1][1][end_effector][:3, 3]
                    record["reached_error"] = float(np.linalg.norm(reached - target))
                result.ik.append(record)
                reached_mm = "n/a" if record["reached_error"] is None else f"{record['reached_error'] * 1e3:.1f} mm"
                log(f"IK target {np.round(target, 3).tolist()}: {record['reason']} (predicted std "
                    f"{record['position_std'] * 1e3:.1f} mm); true end effector {reached_mm} from the target")
            spin_until(executor, lambda: False, timeout=1.5)  # a last diagnostics message
        finally:  # the nodes first: nothing may keep one running in the domain
            result.wall_time_s = time.monotonic() - start
            for process in reversed(processes):
                process.stop()
            recorder.close()

    if monitor.structure is not None:
        result.learned_edges = [[e.parent_id, e.child_id] for e in monitor.structure.edges]
    result.events = [{"step": monitor.step(conversions.seconds_from_stamp(e.header.stamp)), "learner_step": e.step,
                      "kind": e.kind, "model": e.model, "reason": e.reason}
                     for e in monitor.events if e.kind != "input_rejected"]
    result.diagnostics = monitor.diagnostics
    result.scheme_status = monitor.scheme_status
    for stamp, poses in monitor.truth:
        if stamp in monitor.predicted and end_effector in poses:
            error = float(translational_error(monitor.predicted[stamp], poses[end_effector]))
            result.prediction_error.append((monitor.step(stamp), error))
    result.n_observations = monitor.n_observations
    result.recorded = dict(recorder.counts)
    result.rates = {"commands_per_s": len(monitor.truth[:steps]) / babble_time,
                    "observations_per_s": monitor.n_observations / babble_time,
                    # samples scheme_node learnt (its learner's step) per command it received (IK moves included),
                    # from its last /diagnostics
                    "learned_fraction": float(result.scheme_status.get("step", 0))
                    / max(1.0, float(result.scheme_status.get("received.command", 0))),
                    # commands with a prediction to compare with the truth (none before the first body scheme)
                    "predicted_fraction": len(result.prediction_error) / max(1, steps)}
    (out_dir / "summary.json").write_text(json.dumps(asdict(result), indent=1))
    _plot(result, out_dir / "live_demo.png")
    return result


def _plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
    if result.prediction_error:
        steps, errors = np.array(result.prediction_error).T
        ax.plot(steps, errors * 1e3, lw=1, label="end-effector prediction error (vs ground truth)")
    for fault in result.faults:
        step = int(fault.split(":")[0])
        ax.axvline(step, color="k", ls="--", lw=1)
        ax.annotate(fault.split(":")[1], (step, 1.0), xycoords=("data", "axes fraction"), va="top", fontsize=8)
    colors = {"mismatch_detected": "tab:red", "model_replaced": "tab:green", "model_reinstated": "tab:purple",
              "structure_found": "tab:orange", "bootstrap_finished": "tab:gray"}
    for kind, color in colors.items():
        xs = [e["step"] for e in result.events if e["kind"] == kind]
        if xs:
            ax.scatter(xs, [0] * len(xs), color=color, marker="^", zorder=3, label=kind)
    ax.set_xlabel("command")
    ax.set_ylabel("mm")
    ax.set_yscale("symlog", linthresh=10)
    ax.legend(fontsize=7, loc="upper right")
    path_text = "sim_node -> tracker_node -> scheme_node" if result.perception == "rendered" else \
        "sim_node (noise model) -> scheme_node"
    ax.set_title(f"live graph: {path_text} (learning from scratch)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _window_mean(errors, lo, hi):
    values = [e for s, e in errors if lo <= s < hi]
    return float(np.mean(values)) if values else float("nan")


def format_summary(result):
    """The event timeline and a summary table, as text."""
    lines = ["", "Event timeline (step = executed command)"]
    for e in result.events:
        lines.append(f"  {e['step']:5d}  {e['kind']:<20s} {e['reason']}")
    lines.append("")
    lines.append("Diagnostics '/scheme_node: body scheme' level changes: " + ", ".join(
        f"{level}@{step}" for step, level, _ in result.diagnostics))
    lines.append("")
    verdict = "the true tree" if result.structure_learned() else f"NOT the true tree {result.true_edges}"
    lines.append(f"structure learned: {result.learned_edges} ({verdict})")
    errors = result.prediction_error
    marks = [int(f.split(":")[0]) for f in result.faults]
    bounds = [0, *marks, result.steps]
    lines.append("end-effector prediction error (mean, mm), per block and 20 commands after each event:")
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        lines.append(f"  commands {lo:4d}-{hi - 1:4d}: {_window_mean(errors, lo, hi) * 1e3:7.1f}   "
                     f"last 20 of the block: {_window_mean(errors, hi - 20, hi) * 1e3:7.1f}")
    for e in result.events:
        if e["kind"] in ("mismatch_detected", "model_replaced", "model_reinstated"):
            lines.append(f"  after {e['kind']:<18s} at {e['step']:4d}: "
                         f"{_window_mean(errors, e['step'] + 1, e['step'] + 21) * 1e3:7.1f}")
    reached = [r["reached_error"] for r in result.ik if r["reached_error"] is not None]
    spread = f"median {np.median(reached) * 1e3:.1f} mm, max {np.max(reached) * 1e3:.1f} mm" if reached else "n/a"
    lines.append(f"IK: {sum(r['success'] for r in result.ik)}/{len(result.ik)} solved; true end effector from "
                 f"target: {spread}")
    lines.append(f"rates: {result.rates['commands_per_s']:.1f} commands/s, {result.rates['observations_per_s']:.1f} "
                 f"observations/s, {100 * result.rates['learned_fraction']:.0f} % of commands learned as samples "
                 f"({100 * result.rates['predicted_fraction']:.0f} % predicted); "
                 f"wall time {result.wall_time_s:.1f} s")
    if result.recorded:
        topics = sum(map(bool, result.recorded.values()))
        lines.append(f"recorded {sum(result.recorded.values())} messages on {topics} topics into session/ (rosbag2 "
                     f"mcap; Foxglove layout: body_scheme_nodes/config/body_scheme.foxglove.json)")
    return "\n".join(lines)


@command
def main(argv=None):
    """Console entry point."""
    parser = argparse.ArgumentParser(prog="live_demo", description=__doc__.split("\n\n")[0])
    add_robot_arguments(parser)
    parser.add_argument("--steps", type=int, default=300)
    timing = parser.add_mutually_exclusive_group()
    timing.add_argument("--period", type=float, default=0.05, help="s between babbled commands (default 0.05)")
    timing.add_argument("--rate", type=float, default=None, help="babbled commands per second (instead of --period; "
                        "30: a camera's rate)")
    parser.add_argument("--fault", action="append", dest="faults", help="sim fault schedule entry STEP:KIND:ARGS "
                        "(repeatable), e.g. 120:block_joint:2:0.5 and 220:repair; default: those of the demo on the "
                        f"shipped powercube_6dof ({' and '.join(DEMO_FAULTS)}), none on any other robot")
    parser.add_argument("--perception", choices=["noise", "rendered"], default="rendered",
                        help="rendered: camera images through tracker_node (default); noise: the paper's noise model "
                        "straight to scheme_node")
    parser.add_argument("--babble", choices=["sim", "controller"], default="sim",
                        help="sim: sim_node babbles by itself every --period, keeping the last two markers in view "
                             "(default); controller: babble_node drives sim_node through the JointTrajectoryController "
                             "interface, as a real arm (random commands over the whole range: slower to learn)")
    parser.add_argument("--targets", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="out/demo")
    args = parser.parse_args(argv)
    if args.rate is not None and not (args.rate > 0 and args.rate <= 1000):
        parser.error(f"--rate must be in (0, 1000] commands per second, got {args.rate}")
    period = 1.0 / args.rate if args.rate is not None else args.period
    try:
        choice = resolve_robot(args.robot, args.markers, args.camera, args.package_path,
                               pathlib.Path(args.out) / "markers.yaml", args.seed)
    except BodySchemeError as error:
        print(f"live_demo: {error}", file=sys.stderr)
        return 1
    result = run_live_demo(args.out, robot=choice.robot, steps=args.steps, period=period, faults=args.faults,
                           perception=args.perception, n_targets=args.targets, seed=args.seed,
                           markers_path=choice.markers_path, camera=choice.camera, package_path=choice.package_path,
                           babble=args.babble)
    print(format_summary(result))
    print(f"wrote {pathlib.Path(args.out) / 'summary.json'} and {pathlib.Path(args.out) / 'live_demo.png'}")
    return 0 if result.structure_learned() else 1


if __name__ == "__main__":
    sys.exit(main())
