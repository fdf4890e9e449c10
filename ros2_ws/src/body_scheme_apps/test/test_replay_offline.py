"""replay_offline: scheme_node's learning over a bag without ROS, its report, and its errors."""

import contextlib
import io
import json
import pathlib

import pytest
import yaml

from body_scheme_apps.replay_offline import default_part, fault_blocks, main
from body_scheme_core.transforms import translational_error
from body_scheme_nodes.bag_io import read_session, write_session
from body_scheme_nodes.offline_replay import replay_bag
from body_scheme_nodes.settings import SchemeSettings
from body_scheme_sim.robots import load_robot
from body_scheme_sim.sessions import record_session

REPO = pathlib.Path(__file__).resolve().parents[4]
SHIPPED = REPO / "bags" / "joint_blocked_seed0"


def _planar_parameters():
    robot = load_robot("planar_2dof")
    return {"part_ids": list(robot.marker_ids), "joint_names": list(robot.action_joint_names),
            "action_lower": [float(v) for v in robot.action_lower],
            "action_upper": [float(v) for v in robot.action_upper]}


@pytest.fixture(scope="module")
def planar_bag(tmp_path_factory):
    """A 60-step planar session whose second joint gets blocked at step 40, as a bag."""
    session = record_session("planar_2dof", 60, seed=1, faults=["40:block_joint:1:0.3"])
    return write_session(session, tmp_path_factory.mktemp("bags") / "planar")


@pytest.fixture(scope="module")
def shipped_report(tmp_path_factory):
    """replay_offline run on the shipped joint-blocked bag: (exit code, output directory, printed summary)."""
    out = tmp_path_factory.mktemp("replay") / "joint_blocked"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main([str(SHIPPED), "--out", str(out), "--quiet"])
    return code, out, printed.getvalue()


def test_offline_replay_equals_the_learner_fed_the_session_directly(planar_bag):
    """Decoding, pairing and learning over the bag gives the events and predictions of the plain core loop."""
    settings = SchemeSettings.from_parameters(_planar_parameters())
    result = replay_bag(planar_bag, settings)

    session = read_session(planar_bag)
    learner = settings.new_learner()
    events, errors = [], []
    for k in range(session.n_steps):
        truth = dict(zip(session.marker_ids, session.true_poses[k], strict=True))
        predicted = {} if learner.body_scheme is None else learner.predict(session.actions[k])
        errors.append({part: float(translational_error(pose, truth[part])) for part, pose in predicted.items()})
        events += learner.update(session.actions[k], session.observations[k], stamp=k)

    assert len(result.steps) == session.n_steps
    assert [s["command_index"] for s in result.steps] == list(range(session.n_steps))
    assert [e.to_dict() for e in result.events] == [e.to_dict() for e in events]
    assert any(errors), "the session is long enough to predict"
    for record, expected in zip(result.steps, errors, strict=True):
        assert sorted(record["prediction"]) == sorted(expected)
        for part, error in expected.items():
            assert record["prediction"][part][0] == pytest.approx(error, abs=1e-12)
    assert sum(result.rejected.values()) == 0


@pytest.mark.slow
def test_shipped_bag_finds_the_true_structure_detects_the_block_and_recovers(shipped_report):
    """On joint_blocked_seed0 bootstrapping finds powercube_6dof's chain, the block is detected and repaired."""
    code, out, _ = shipped_report
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    robot = load_robot("powercube_6dof")
    truth = {frozenset(edge): list(robot.path_actions(*edge)) for edge in robot.marker_tree_edges()}
    events = report["events"]

    boot = next(e for e in events if e["kind"] == "bootstrap_finished")
    at_boot = next(s for s in report["steps"] if s["step"] == boot["step"])
    assert {frozenset((e["parent"], e["child"])) for e in at_boot["edges"]} == set(truth)
    assert boot["step"] < 100, "bootstrapped before the fault"
    final = report["final"]
    assert {frozenset((e["parent"], e["child"])): e["actions"] for e in final["edges"]} == truth
    assert final["phase"] == "steady" and all(e["valid"] for e in final["edges"])

    def first(kind, start, stop):
        return next((e for e in events if e["kind"] == kind and start <= e["step"] < stop), None)

    blocked = first("mismatch_detected", 100, 200)
    assert blocked is not None and {blocked["parent"], blocked["child"]} == {6, 7}
    assert first("model_replaced", blocked["step"], 200) or first("model_reinstated", blocked["step"], 200)
    assert first("mismatch_detected", 0, 100) is None, "no false alarm before the fault"
    assert first("model_reinstated", 200, 300) is not None, "the repair brings back the remembered model"
    assert first("model_reinstated", 300, 400) is not None, "the second block recalls the model of the first"


@pytest.mark.slow
def test_the_readme_quotes_the_replays_figures(shipped_report):
    """The README's per-block end-effector errors of ``make replay`` are the ones the replay gives (it is
    deterministic: one math thread, a shipped bag)."""
    code, out, _ = shipped_report
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    figures = " / ".join(f"{1e3 * b['mean_end_effector_error']:.0f}" for b in report["blocks"])
    readme = " ".join((REPO / "README.md").read_text(encoding="utf-8").split())
    assert f"predicts the end effector to {figures} mm in the four protocol blocks" in readme, figures


@pytest.mark.slow
def test_report_files_are_well_formed(shipped_report):
    """report.json is strict JSON with one record per step, events.txt lists faults and events, errors.png a PNG."""
    code, out, printed = shipped_report
    assert code == 0

    def no_nan(name):
        raise AssertionError(f"{name} in report.json")

    report = json.loads((out / "report.json").read_text(), parse_constant=no_nan)
    assert report["n_commands"] == 400 and len(report["steps"]) == 400
    assert report["end_effector"] == 7
    assert report["settings"]["config"]["test_window"] == 15
    stamps = [s["stamp"] for s in report["steps"]]
    assert stamps == sorted(stamps)
    for record in report["steps"]:
        assert set(record) == {"step", "command_index", "stamp", "phase", "edges", "end_effector"}
    predicted = [s["end_effector"]["trans_error"] for s in report["steps"] if s["end_effector"]]
    assert len(predicted) > 300 and all(0 <= e < 2.0 for e in predicted)
    assert [b["label"] for b in report["blocks"]] == ["normal", "block_joint:5:0.8", "repair", "block_joint:5:0.8"]
    assert all(b["mean_end_effector_error"] > 0 for b in report["blocks"])

    timeline = (out / "events.txt").read_text()
    assert "---- step 100: block_joint:5:0.8 ----" in timeline and "---- step 200: repair ----" in timeline
    for kind in {e["kind"] for e in report["events"]}:
        assert kind in timeline
    png = (out / "errors.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000

    assert "final body scheme" in printed and "6-7" in printed
    assert "mismatch_detected 3" in printed
    assert printed.count(" mm over ") == 4


def test_params_file_and_part_are_used(planar_bag, tmp_path):
    """--params sets the robot's parts and joints, --part the end effector of the report."""
    params = tmp_path / "planar.yaml"
    params.write_text(yaml.safe_dump({"scheme_node": {"ros__parameters": _planar_parameters()}}))
    out = tmp_path / "out"
    assert main([str(planar_bag), "--params", str(params), "--out", str(out), "--part", "2", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["end_effector"] == 2 and report["settings"]["part_ids"] == [1, 2, 3]
    assert [b["label"] for b in report["blocks"]] == ["normal", "block_joint:1:0.3"]


def test_corrupt_or_missing_bag_exits_with_a_clear_error(planar_bag, tmp_path, capsys):
    """A corrupt or missing bag gives exit code 1 and a message naming the problem, not a traceback."""
    broken = tmp_path / "broken"
    broken.mkdir()
    for part in planar_bag.iterdir():
        data = part.read_bytes()
        (broken / part.name).write_bytes(data[: len(data) // 2] if part.suffix == ".mcap" else data)
    assert main([str(broken), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert "corrupt" in capsys.readouterr().err
    assert main([str(tmp_path / "nothing"), "--quiet"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_parameter_file_of_another_robot_is_refused(planar_bag, tmp_path, capsys):
    """The default (6-DOF) parameters on a planar bag are refused with the joint names, exit code 1."""
    assert main([str(planar_bag), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert "joint_names" in capsys.readouterr().err


def test_default_part_is_the_farthest_from_the_root():
    """The deepest part of the tree is the end effector; ties go to the highest id."""
    assert default_part([(1, 2), (2, 3), (1, 4)], root=1) == 3
    assert default_part([(1, 2), (1, 3)], root=1) == 3
    assert default_part([(5, 1), (1, 2), (2, 9), (5, 4)], root=5) == 9


def test_fault_blocks_follow_the_session_timeline():
    """Fault entries split the commands into labelled blocks; repair ends a fault block."""
    info = {"faults": [[10, "10:block_joint:1:0.3"], [20, "20:repair"]]}
    blocks = fault_blocks(info, 30)
    assert [(b["start"], b["stop"], b["label"], b["fault"]) for b in blocks] == [
        (0, 10, "normal", False), (10, 20, "block_joint:1:0.3", True), (20, 30, "repair", False)]
    assert fault_blocks(None, 5) == [{"start": 0, "stop": 5, "label": "normal", "fault": False}]
    assert [b["stop"] for b in fault_blocks(info, 15)] == [10, 15]
    long = {"faults": [[5, "5:deform_limb:tool_joint:0.1:0.7853981633974483:0.0:0.0"]]}
    assert fault_blocks(long, 9)[1]["label"] == "deform_limb:tool_joint:0.1:0.785:0:0"
