"""The calibrate command: a saved state to a learned URDF and a calibration report against the shipped robot."""

import json
import math
import pathlib
from types import SimpleNamespace

import numpy as np
import pytest
from urdf_parser_py.urdf import URDF

from body_scheme_apps.calibrate import main, seldom_taken, verdict
from body_scheme_apps.robot_option import resolve_robot
from body_scheme_core.learning.learner import BodySchemeLearner
from body_scheme_core.learning.persistence import save_state
from body_scheme_core.models import GPModel, RevoluteModel
from body_scheme_core.prediction.scheme import BodyScheme
from body_scheme_core.world import Marker, load_markers_yaml, make_session, resolve_meshes, tree_from_urdf
from body_scheme_sim.robots import load_robot, robot_files


@pytest.mark.slow
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
    printed = capsys.readouterr().out
    assert "max: axis" in printed
    assert "verdict: a true body scheme of the robot (2 edges, phase steady)" in printed, printed[-800:]
    assert "worst joint: " in printed and f"files: {out / 'learned.urdf'}" in printed


def test_the_verdict_says_when_there_is_no_true_body_scheme(tmp_path):
    """Before any command the learner has no body scheme: the verdict says NOT, and what to do."""
    robot = load_robot("planar_2dof")
    learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, action_lower=robot.action_lower,
                                action_upper=robot.action_upper)
    text = verdict(learner, robot, None, tmp_path)
    assert text.startswith("verdict: NOT a true body scheme of the robot (no body scheme, phase bootstrapping)")
    assert "worst joint" not in text and "report.txt" not in text and "not joints" not in text


def test_simulate_names_the_markers_the_camera_saw_and_the_tracker_seldom_took():
    """The Panda's base marker was in view in most pictures and refused as ambiguous in nearly all: a user is told
    which marker, on which link, and what the tracker refused; a marker taken in half of its pictures is not named."""
    tree = load_robot("powercube_6dof")
    session = make_session(tree, 10, seed=0, visibility=1.0)
    ids = session.marker_ids
    session.visible_truth = np.ones((10, len(ids)), dtype=bool)
    session.visible_truth[:, -1] = False  # never in view, never taken: the camera's business, not the tracker's
    for k, observed in enumerate(session.observations):
        observed.pop(ids[-1])
        if k >= 2:
            observed.pop(ids[0])
        if k >= 5:
            observed.pop(ids[1])
    session.tracker_rejected = {"ambiguous pose": 8, "degenerate detection": 1}
    lines = seldom_taken(session, tree)
    assert lines[0] == (f"marker {ids[0]} on {tree.marker(ids[0]).link}: in view in 10 of 10 pictures, taken by the "
                        f"tracker in 2")
    assert len(lines) == 2 and "ambiguous pose 8, degenerate detection 1" in lines[1]
    session = make_session(tree, 10, seed=0, visibility=1.0)
    session.visible_truth, session.tracker_rejected = np.ones((10, len(ids)), dtype=bool), {"ambiguous pose": 3}
    assert seldom_taken(session, tree) == []


def test_the_verdict_names_the_edges_that_are_gps_not_joints(tmp_path):
    """A true tree whose edge 2->3 is a GP (right actions, no rigid joint): true, and the GP edge named as no joint."""
    robot = load_robot("planar_2dof")
    A = np.random.default_rng(0).uniform(robot.action_lower, robot.action_upper, (20, robot.n_actions))
    poses = [robot.marker_poses(a) for a in A]
    first = RevoluteModel(1, 2, (0,)).fit(A, np.stack([np.linalg.inv(p[1]) @ p[2] for p in poses]))
    gp = GPModel(2, 3, (1,)).fit(np.zeros((3, 2)), np.stack([np.eye(4)] * 3))
    learner = SimpleNamespace(body_scheme=BodyScheme(robot.marker_ids, 1, [first, gp]), phase="steady",
                              trained_range=lambda: (robot.action_lower, robot.action_upper))
    text = verdict(learner, robot, None, tmp_path)
    assert text.startswith("verdict: a true body scheme of the robot (2 edges, phase steady)"), text
    assert "\nnot joints: 1 of 2 edges are no URDF joint (2->3 (gp)): learned.urdf fixes them at mid-range" in text


def test_unreadable_input_is_one_line_and_exit_code_1(tmp_path, capsys):
    (tmp_path / "state.json").write_text("{not json")
    assert main(["--state", str(tmp_path / "missing.json"), "--out", str(tmp_path / "out")]) == 1
    assert main(["--state", str(tmp_path / "state.json"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("calibrate: ") for line in err), err


@pytest.mark.slow  # a whole simulated session and calibration
def test_a_robots_urdf_alone_is_enough_to_simulate_and_calibrate(tmp_path, capsys):
    """--simulate <a real arm's URDF> needs no other file: markers are planned (markers.yaml), the camera frames them,
    a body scheme is learned and calibrated (here the noise model at the tracker's accuracy, for speed; make
    experiments runs the rendered images: yourrobot)."""
    import pybullet_data

    urdf = f"{pybullet_data.getDataPath()}/kuka_iiwa/model.urdf"
    out = tmp_path / "iiwa"
    assert main(["--simulate", urdf, "--perception", "noise", "--steps", "400", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "planned 8 markers" in printed and "camera at" in printed
    names = {p.name for p in out.iterdir()}
    assert {"markers.yaml", "markers.pdf", "learned.urdf", "report.json", "report.png"} <= names
    assert any(name.startswith("markers") and name.endswith(".png") for name in names)  # one png per page
    assert "and the sheet to print" in printed and "verdict: a true body scheme of the robot" in printed
    assert f"its camera {out / 'camera.yaml'}" in printed  # the camera the markers were planned for, kept with them
    lines = []
    again = resolve_robot(urdf, out / "markers.yaml", log=lines.append).camera  # a later command with these markers
    assert lines == [f"camera of {out / 'camera.yaml'} (the one the markers were planned for; --camera overrides it)"]
    assert (again.width, again.height, again.fx) == (1280, 960, pytest.approx(640.0 / math.tan(math.radians(30))))
    replanned = resolve_robot(urdf, camera="auto", plan_to=tmp_path / "again" / "markers.yaml", log=lines.append)
    assert np.allclose(again.world2camera, replanned.camera.world2camera, atol=1e-9)  # auto, as the first run's
    with pytest.raises(ValueError, match="plan_to"):
        resolve_robot(urdf, camera="auto")  # planning needs a place for its files (never the working directory)
    report = json.loads((out / "report.json").read_text())
    assert len(report["joints"]) == 7 and report["max_axis_deg"] < 3.0
    _check_the_calibrated_urdf(out, pathlib.Path(urdf), pybullet_data.getDataPath())


def _check_the_calibrated_urdf(out, nominal_urdf, package_path):
    """calibrated.urdf is the robot's file (its links, meshes, limits) with moved joint origins: it loads in
    urdf_parser_py and in pybullet (its meshes resolved as the nominal file's), and with calibrated.markers.yaml its
    forward kinematics is the learned body scheme's (learned.urdf) to 0.1 mm."""
    import pybullet

    text = (out / "calibrated.urdf").read_text()
    calibrated, nominal = URDF.from_xml_string(text), URDF.from_xml_string(nominal_urdf.read_text())
    assert [link.name for link in calibrated.links] == [link.name for link in nominal.links]
    assert [(j.name, j.type, j.limit and j.limit.upper) for j in calibrated.joints] == \
        [(j.name, j.type, j.limit and j.limit.upper) for j in nominal.joints]
    assert "<calibration" not in text and text.count("<mesh") == nominal_urdf.read_text().count("<mesh") > 0
    resolved, missing = resolve_meshes(text, nominal_urdf.parent, [package_path])
    assert missing == []
    (out / "resolved.urdf").write_text(resolved)
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(out / "resolved.urdf"), physicsClientId=client)
        assert pybullet.getNumJoints(body, physicsClientId=client) == len(nominal.joints)
    finally:
        pybullet.disconnect(client)
    markers = load_markers_yaml(out / "calibrated.markers.yaml")
    tree = tree_from_urdf(text, markers)
    learned_text = (out / "learned.urdf").read_text()
    learned = tree_from_urdf(learned_text, [Marker(m.id, f"marker_{m.id}") for m in markers],
                             joint_actions={name: k for k, name in enumerate(tree.action_joint_names)})
    root = min(m.id for m in markers)
    rng = np.random.default_rng(0)
    diff = (out / "calibrated_diff.txt").read_text()
    assert all(name in diff for name in tree.action_joint_names)
    for a in rng.uniform(-0.5, 0.5, size=(20, tree.n_actions)):
        got, want = tree.marker_poses(a), learned.marker_poses(a)
        for m in markers:
            relative = np.linalg.inv(got[root]) @ got[m.id], np.linalg.inv(want[root]) @ want[m.id]
            assert np.linalg.norm(relative[0][:3, 3] - relative[1][:3, 3]) < 1e-4


def _write(path, text):
    path.write_text(text)
    return str(path)


def test_every_failure_to_load_a_robot_is_one_line(tmp_path, capsys):
    """A missing URDF, a joint type a tree cannot hold, XML that is not URDF, a mimic of nothing and meshes that
    cannot be found (so nothing to put a marker on) each give one line and exit code 1, no traceback."""
    link = '<link name="{}"><collision><geometry><mesh filename="package://nope/m.stl"/></geometry></collision></link>'
    robots = {
        "missing": str(tmp_path / "missing.urdf"),
        "floating": _write(tmp_path / "floating.urdf", '<robot name="r"><link name="a"/><link name="b"/><joint '
                                                       'name="j" type="floating"><parent link="a"/><child link="b"/>'
                                                       '</joint></robot>'),
        "not_xml": _write(tmp_path / "broken.urdf", "<robot name='r'><link name='a'>"),
        "mimic": _write(tmp_path / "mimic.urdf", '<robot name="r"><link name="a"/><link name="b"/><joint name="j" '
                                                 'type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 '
                                                 '1"/><mimic joint="x"/></joint></robot>'),
        "meshes": _write(tmp_path / "meshes.urdf", f'<robot name="r">{link.format("a")}{link.format("b")}<joint '
                                                   f'name="j" type="revolute"><parent link="a"/><child link="b"/>'
                                                   f'<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" '
                                                   f'velocity="1"/></joint></robot>'),
    }
    for name, urdf in robots.items():
        assert main(["--simulate", urdf, "--steps", "5", "--out", str(tmp_path / name)]) == 1, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("calibrate: "), (name, err)
    assert "--package-path" in err[0]

    # A camera.yaml beside the markers that is not the plan's (a camera driver's calibration file): one line that says
    # why it was read and how to do without it.
    urdf_path, markers_path = robot_files("planar_2dof")
    (tmp_path / "mine").mkdir()
    markers = tmp_path / "mine" / "markers.yaml"
    markers.write_text(markers_path.read_text())
    (tmp_path / "mine" / "camera.yaml").write_text("image_width: 640\ncamera_matrix: {rows: 3, cols: 3}\n")
    assert main(["--simulate", str(urdf_path), "--markers", str(markers), "--steps", "5", "--out",
                 str(tmp_path / "mine" / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"calibrate: camera file {tmp_path / 'mine' / 'camera.yaml'}: "), err
    assert err[0].endswith('--camera auto or --camera "x y z roll pitch yaw" does without it'), err


@pytest.mark.slow  # 2 s: two sessions learnt
def test_the_accuracy_report_cross_validates_and_two_sessions_give_the_repeatability(tmp_path, capsys):
    """accuracy.json: held-out errors at the sensor's noise and close to the true robot's, small joint stds, an
    error curve that falls with the poses; repeatability.json: two sessions' learned bodies agree per joint."""
    urdf_path, markers_path = robot_files("planar_2dof")
    robot = load_robot("planar_2dof")
    for seed in (0, 1):
        session = make_session(robot, 150, seed=seed, sigma_trans=0.005, sigma_rot=math.radians(2.0))
        learner = BodySchemeLearner(robot.marker_ids, robot.n_actions, action_lower=robot.action_lower,
                                    action_upper=robot.action_upper)
        for actions, observations in zip(session.actions, session.observations, strict=True):
            learner.update(actions, observations)
        save_state(learner, tmp_path / f"state{seed}.json")
    out = tmp_path / "out"
    assert main(["--state", str(tmp_path / "state0.json"), "--urdf", str(urdf_path), "--markers", str(markers_path),
                 "--repeat-state", str(tmp_path / "state1.json"), "--out", str(out)]) == 0
    accuracy = json.loads((out / "accuracy.json").read_text())
    assert 2.0 < accuracy["cv_mm"] < 8.0  # 5 mm 3D RMS noise: a mean distance of about 4.6 mm
    assert accuracy["cv_mm"] < 1.2 * accuracy["nominal_cv_mm"]
    assert sorted(accuracy["cv"]) == sorted([*map(str, robot.marker_ids), "all"])
    assert [row["joint"] for row in accuracy["joint_std"]] == list(robot.action_joint_names)
    assert all(row["axis_deg"] < 1.0 and row["origin_mm"] < 5.0 for row in accuracy["joint_std"])
    assert accuracy["curve"][0]["cv_mm"] > accuracy["curve"][-1]["cv_mm"]
    assert (out / "accuracy.png").stat().st_size > 5_000 and "jackknife" in (out / "accuracy.txt").read_text()
    repeat = json.loads((out / "repeatability.json").read_text())
    assert [row["joint"] for row in repeat["joints"]] == list(robot.action_joint_names)
    assert repeat["max_axis_deg"] < 2.0 and repeat["max_origin_mm"] < 5.0
    assert "held-out prediction error" in capsys.readouterr().out
