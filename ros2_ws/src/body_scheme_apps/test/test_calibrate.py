"""The calibrate command: a saved state to a learned URDF and a calibration report against the shipped robot."""

import json
import math

from body_scheme_apps.calibrate import main
from urdf_parser_py.urdf import URDF

from body_scheme_core.learner import BodySchemeLearner
from body_scheme_core.persistence import save_state
from body_scheme_core.world import make_session
from body_scheme_sim.robots import load_robot, robot_files


def test_a_saved_state_gives_a_urdf_and_a_report_in_text_json_and_png(tmp_path, capsys):
    """From scheme_node's state file and the shipped URDF + markers: learned.urdf parses, the report is small."""
    urdf_path, markers_path = robot_files("planar_2dof")
    robot = load_robot("planar_2dof")
    session = make_session(robot, 150, seed=0, sigma_trans=0.005, sigma_rot=math.radians(2.0))
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, action_lower=robot.action_lower,
                                action_upper=robot.action_upper)
    for actions, observations in zip(session.actions, session.observations, strict=True):
        learner.update(actions, observations)
    save_state(learner, tmp_path / "state.json")
    out = tmp_path / "out"
    assert main(["--state", str(tmp_path / "state.json"), "--urdf", str(urdf_path), "--markers", str(markers_path),
                 "--out", str(out)]) == 0
    robot_urdf = URDF.from_xml_string((out / "learned.urdf").read_text())
    assert sorted(j.name for j in robot_urdf.joints if j.type == "revolute") == sorted(robot.action_joint_names)
    report = json.loads((out / "report.json").read_text())
    assert report["max_axis_deg"] < 2.0 and report["max_origin_mm"] < 5.0
    assert "axis deg" in (out / "report.txt").read_text() and (out / "report.png").stat().st_size > 10_000
    assert "max: axis" in capsys.readouterr().out


def test_unreadable_input_is_one_line_and_exit_code_1(tmp_path, capsys):
    (tmp_path / "state.json").write_text("{not json")
    assert main(["--state", str(tmp_path / "missing.json"), "--out", str(tmp_path / "out")]) == 1
    assert main(["--state", str(tmp_path / "state.json"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("calibrate: ") for line in err), err
