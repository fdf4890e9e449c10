"""plan_markers on a URDF it was not written for: the marker file, the sheet, the camera and scheme_node's parameter
file for that robot, which the node's own settings reader takes."""

import pathlib

import pybullet_data
import pytest
import yaml

from body_scheme_apps.plan_markers import main
from body_scheme_apps.robot_option import scheme_parameters_path
from body_scheme_nodes.settings import SchemeSettings
from body_scheme_sim.robots import load_robot

XARM = pathlib.Path(pybullet_data.getDataPath()) / "xarm" / "xarm6_robot.urdf"


@pytest.mark.slow
def test_the_plan_comes_with_scheme_nodes_parameters_for_the_robot(tmp_path, capsys):
    assert main(["--robot", str(XARM), "--out", str(tmp_path), "--dpi", "72"]) == 0
    assert "scheme_node.yaml (scheme_node's parameters for this robot" in capsys.readouterr().out
    for name in ("markers.yaml", "markers.pdf", "camera.yaml", "scheme_node.yaml"):
        assert (tmp_path / name).is_file(), name
    tree = load_robot(str(XARM), tmp_path / "markers.yaml")
    text = (tmp_path / "scheme_node.yaml").read_text()
    assert "# Written for " in text and "# marker ids of the body parts" in text  # the template's comments kept
    parameters = yaml.safe_load(text)["/**"]["ros__parameters"]
    assert parameters["part_ids"] == [int(i) for i in tree.marker_ids]
    assert parameters["joint_names"] == list(tree.action_joint_names)
    assert all(isinstance(v, float) for v in parameters["action_lower"] + parameters["action_upper"])
    assert parameters["learner"]["sigma_trans"] == 0.01 and parameters["learner"]["sigma_rot"] == 0.087
    settings = SchemeSettings.from_yaml(tmp_path / "scheme_node.yaml")
    assert list(settings.part_ids) == [int(i) for i in tree.marker_ids]
    assert list(settings.action_lower) == pytest.approx(tree.action_lower)
    assert list(settings.action_upper) == pytest.approx(tree.action_upper)


def test_the_parameter_file_is_named_after_its_marker_file_so_none_overwrites_another():
    assert scheme_parameters_path("out/your-robot/markers.yaml") == pathlib.Path("out/your-robot/scheme_node.yaml")
    assert scheme_parameters_path("bags/run1.markers.yaml") == pathlib.Path("bags/run1.scheme_node.yaml")
    assert scheme_parameters_path("bags/run2.markers.yaml") == pathlib.Path("bags/run2.scheme_node.yaml")
    assert scheme_parameters_path("plates.yaml") == pathlib.Path("plates.scheme_node.yaml")
    assert scheme_parameters_path("mymarkers.yaml") == pathlib.Path("mymarkers.scheme_node.yaml")
