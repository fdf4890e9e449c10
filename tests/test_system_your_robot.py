"""docs/your-robot.md rehearsed end to end with its commands as written: plan the markers of a URDF (step 2), run
the graph a real arm uses (step 4: tracker_node, scheme_node from the planned parameter file, babble_node with the
documented parameters), with sim_node in place of the arm's JointTrajectoryController and of the camera, placed where
the plan assumes; learn the body scheme, save it with ``body-scheme`` and write the calibration report (step 6).

Only what the doc leaves to the user is filled in: the URDF's path and the planned part ids. Files are where the doc
puts them, relative to the working directory, and ``~`` is a home of the test's own."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory
from workspace import documented_commands

from body_scheme_msgs.msg import BodySchemeStructure
from body_scheme_sim.robots import ROBOTS_DIR, load_robot

pytestmark = pytest.mark.system

#: "Your robot": a URDF only (the shipped arm's own marker file is not used; the planner places the markers).
URDF = ROBOTS_DIR / "arm_4dof.urdf"
PLACEHOLDERS = {"path/to/your_robot.urdf": str(URDF)}
#: Action signals before the rehearsal gives up on the true tree (as many as step 3's rehearsals babble).
MAX_COMMANDS = 600


def _documented(*prefix, fill=None):
    """The commands of docs/your-robot.md that start with ``prefix``, as written but for :data:`PLACEHOLDERS` (and
    ``fill``)."""
    fill = {**PLACEHOLDERS, **(fill or {})}
    found = [[_filled(word, fill) for word in words] for doc, words in documented_commands()
             if doc == "your-robot.md" and tuple(words[:len(prefix)]) == prefix]
    assert found, f"docs/your-robot.md has no command {' '.join(prefix)}"
    return found


def _filled(word, fill):
    for placeholder, value in fill.items():
        word = word.replace(placeholder, value)
    return word


def _ros_args(prefix, fill):
    """The ``--ros-args`` of the documented ``ros2 run body_scheme_nodes <node>`` command, ``<...>`` filled in."""
    (words,) = _documented("ros2", "run", "body_scheme_nodes", *prefix)
    args = [_filled(arg, fill) for arg in words[words.index("--ros-args") + 1:]]
    assert not any("<" in arg for arg in args), args
    return args


def _run(words, env):
    """Run a documented shell command (``python``: this interpreter; a leading ``~/``: the test's home)."""
    words = [sys.executable if word == "python" else word for word in words]
    words = [env["HOME"] + word[1:] if word.startswith("~/") else word for word in words]
    done = subprocess.run(words, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, (words, done.stdout[-3000:], done.stderr[-3000:])
    return done.stdout


@pytest.fixture
def planned(ros_env, tmp_path, monkeypatch):
    """Step 2 (plan, print) in the test's working directory: ``(environment, part ids, true marker-tree edges)``."""
    monkeypatch.chdir(tmp_path)
    env = dict(ros_env, HOME=str(tmp_path / "home"))
    (plan,) = _documented("python", "-m", "body_scheme_apps.plan_markers")
    printed = _run(plan, env)
    for name in ("markers.yaml", "markers.pdf", "camera.yaml", "scheme_node.yaml"):
        assert (tmp_path / "markers" / name).is_file(), (name, printed)
    parameters = yaml.safe_load((tmp_path / "markers" / "scheme_node.yaml").read_text())["/**"]["ros__parameters"]
    tree = load_robot(URDF, markers_path=tmp_path / "markers" / "markers.yaml")
    return env, [int(i) for i in parameters["part_ids"]], {frozenset(edge) for edge in tree.marker_tree_edges()}


def test_the_simulated_rehearsal_runs_the_graph_on_your_robot_without_the_shipped_arms_faults(planned, tmp_path):
    """Step 3's live_demo as written: the whole graph on the planned markers, the camera where the plan put it; no
    fault of the shipped arm (its default blocked a joint of another robot); exit 0 exactly when the true tree was
    learnt. Then step 3's calibrate --simulate as written: the report of an offline rehearsal. Whether 600 commands
    suffice is measured (the closing notes), not asserted: learning from scratch varies from run to run, as the doc
    says."""
    env, _, true_edges = planned
    (demo,) = _documented("python", "-m", "body_scheme_apps.live_demo")
    done = subprocess.run([sys.executable, *demo[1:]], env=env, capture_output=True, text=True, timeout=900)
    summary = json.loads((tmp_path / "out" / "demo" / "summary.json").read_text())
    assert summary["faults"] == [] and "IK:" in done.stdout, (done.stdout[-3000:], done.stderr[-3000:])
    assert "camera of markers/camera.yaml (the one the markers were planned for" in done.stdout  # no --camera needed
    learned = {frozenset(edge) for edge in summary["learned_edges"]}
    assert done.returncode == (0 if learned == true_edges else 1), (done.returncode, learned, done.stdout[-3000:])
    assert {frozenset(edge) for edge in summary["true_edges"]} == true_edges

    # Step 4's print_markers as written (on the planned file: what a user who edits it runs again).
    (sheet,) = _documented("python", "-m", "body_scheme_apps.print_markers")
    (tmp_path / "markers" / "markers.pdf").unlink()
    assert _run(sheet, env).startswith("wrote markers/markers.pdf") and (tmp_path / "markers" / "markers.pdf").is_file()

    # The second command of step 3: learn offline in the simulator, with the plan's camera, and write the report.
    (rehearsal,) = _documented("python", "-m", "body_scheme_apps.calibrate", "--simulate")
    printed = _run(rehearsal, env)
    out = tmp_path / rehearsal[rehearsal.index("--out") + 1]
    assert "camera of markers/camera.yaml (the one the markers were planned for" in printed, printed
    for name in ("learned.urdf", "calibrated.urdf", "report.txt", "report.json", "report.png", "accuracy.txt"):
        assert (out / name).is_file(), (name, printed)
    assert printed.count("\nverdict: ") == 1 and f"files: {rehearsal[rehearsal.index('--out') + 1]}/learned.urdf" \
        in printed, printed  # true or not is measured (the closing notes), as for live_demo


def test_the_rehearsal_plans_babbles_over_the_controller_learns_and_reports(planned, start_node, ros_node, spin_until,
                                                                             tmp_path):
    env, part_ids, true_edges = planned

    # Step 4's graph, with sim_node as the arm and the camera (the camera where the plan put it).
    structures, commands, trajectories = [], [], []
    ros_node.create_subscription(BodySchemeStructure, "body_scheme/structure", structures.append, 10)
    ros_node.create_subscription(JointState, "joint_commands", commands.append, 100)
    ros_node.create_subscription(JointTrajectory, "joint_trajectory_controller/joint_trajectory",
                                 trajectories.append, 100)
    babble_args = _ros_args(("babble_node",), {"<the part_ids of markers/scheme_node.yaml>":
                                               ", ".join(map(str, part_ids))})
    nodes = [start_node("body_scheme_nodes", name, {}, env_overrides=env, ros_args=args)
             for name, args in (("tracker_node", _ros_args(("tracker_node",), {})),
                                ("scheme_node", _ros_args(("scheme_node",), {})), ("babble_node", babble_args))]
    camera = yaml.safe_load((tmp_path / "markers" / "camera.yaml").read_text())
    nodes.append(start_node("body_scheme_nodes", "sim_node", {
        "robot": str(URDF), "markers_path": "markers/markers.yaml", "perception_mode": "rendered", **camera},
        env_overrides=env))

    def learned():
        return structures and {frozenset((e.parent_id, e.child_id)) for e in structures[-1].edges} == true_edges \
            and all(e.valid for e in structures[-1].edges)

    # However slow the machine: waited for as long as babble_node keeps sending action signals, up to MAX_COMMANDS.
    spin_until(lambda: learned() or len(commands) >= MAX_COMMANDS, timeout=120, progress=lambda: len(commands))
    assert learned(), (
        len(commands), structures[-1] if structures else None, *(node.output()[-2000:] for node in nodes))
    assert all(node.running() for node in nodes)

    # Every move within the documented limits: the controller's cubic peaks at 1.5 d / T and 6 d / T^2.
    documented = dict(arg.split(":=", 1) for arg in babble_args if ":=" in arg)
    max_velocity, max_acceleration = float(documented["max_velocity"]), float(documented["max_acceleration"])
    assert trajectories
    previous = np.zeros(len(trajectories[0].joint_names))  # sim_node's arm starts at the zero posture
    for trajectory in trajectories:
        goal = np.array(trajectory.points[-1].positions)
        duration = trajectory.points[-1].time_from_start.sec + 1e-9 * trajectory.points[-1].time_from_start.nanosec
        distance = np.max(np.abs(goal - previous))
        assert 1.5 * distance <= max_velocity * duration + 1e-6, (distance, duration)
        assert 6.0 * distance <= max_acceleration * duration ** 2 + 1e-6, (distance, duration)
        previous = goal

    # Step 6: save with body-scheme, then the report from the saved state.
    (save,) = _documented("body-scheme", "save")
    _run(save, env)
    (state,) = (tmp_path / "home" / ".ros" / "body_scheme").glob("*.json")
    (report,) = _documented("python", "-m", "body_scheme_apps.calibrate", "--state")
    printed = _run(report, env)
    out = tmp_path / report[report.index("--out") + 1]
    for name in ("learned.urdf", "report.txt", "report.json", "report.png"):
        assert (out / name).is_file(), (name, printed)
    assert "verdict: a true body scheme of the robot" in printed, printed
    assert os.path.getsize(state) > 0
