"""Static checks of the launch files shipped for ROS 2 from apt.

``launch`` and ``launch_ros`` are not on PyPI, so the launch files cannot run here (the demo and the system tests
start the same nodes as processes, body_scheme_nodes/graph.py). These checks catch what would break them anyway: a
syntax error, a launch file not installed, a node executable that does not exist, a parameter file that is not
installed, or a parameter override the node does not declare (its shipped YAML lists exactly what it declares; the
node tests check that).
"""

from __future__ import annotations

import ast
import pathlib

import pytest
import yaml
from ament_index_python.packages import get_package_share_directory

from body_scheme_nodes.graph import executable

SRC = pathlib.Path(__file__).resolve().parents[1] / "ros2_ws" / "src"
LAUNCH_FILES = sorted(SRC.glob("*/launch/*.launch.py"))


def _flat_keys(mapping, prefix=""):
    keys = set()
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        keys |= _flat_keys(value, name + ".") if isinstance(value, dict) else {name}
    return keys


def declared_parameters(package, node):
    """Parameter names in the node's shipped YAML (``config/<node>.yaml``), dotted for nested ones."""
    data = yaml.safe_load((SRC / package / "config" / f"{node}.yaml").read_text())
    return _flat_keys(data["/**"]["ros__parameters"])


def launched_nodes(path):
    """``[(package, executable, {override: value node})]`` of every ``Node(...)`` call in a launch file."""
    nodes = []
    for call in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "Node":
            keywords = {k.arg: k.value for k in call.keywords}
            overrides = {}
            for item in getattr(keywords.get("parameters"), "elts", []):
                if isinstance(item, ast.Dict):
                    overrides.update({ast.literal_eval(k): v for k, v in zip(item.keys, item.values, strict=True)})
            package = ast.literal_eval(keywords["package"])
            nodes.append((package, ast.literal_eval(keywords["executable"]), overrides))
    return nodes


def test_launch_files_are_shipped():
    assert {p.name for p in LAUNCH_FILES} == {"live_graph.launch.py", "body_scheme.launch.py"}


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_is_installed_and_starts_existing_nodes_with_declared_parameters(path):
    package = path.parents[1].name
    installed = pathlib.Path(get_package_share_directory(package)) / "launch" / path.name
    assert installed.exists(), f"{installed} missing: setup.py data_files must install launch/"
    nodes = launched_nodes(path)
    assert nodes, f"{path.name} starts no Node"
    for node_package, node, overrides in nodes:
        assert executable(node_package, node).exists()
        shipped = pathlib.Path(get_package_share_directory(node_package)) / "config" / f"{node}.yaml"
        assert shipped.exists(), f"{shipped} is not installed"
        unknown = set(overrides) - declared_parameters(node_package, node)
        assert not unknown, f"{path.name}: {node} does not declare {sorted(unknown)}"


def test_the_rviz_config_and_foxglove_layout_are_installed_and_show_scheme_nodes_topics():
    """Neither RViz nor Foxglove runs here: check that both files are installed, parse, and name the topics
    scheme_node publishes (body_scheme_nodes.view) and its default frame."""
    import json

    share = pathlib.Path(get_package_share_directory("body_scheme_nodes")) / "config"
    rviz = yaml.safe_load((share / "body_scheme.rviz").read_text())
    displays = {d["Class"]: d for d in rviz["Visualization Manager"]["Displays"]}
    assert displays["rviz_default_plugins/MarkerArray"]["Topic"]["Value"] == "/body_scheme/markers"
    assert displays["rviz_default_plugins/PoseArray"]["Topic"]["Value"] == "/body_scheme/poses"
    assert displays["rviz_default_plugins/RobotModel"]["Description Topic"]["Value"] == \
        "/body_scheme/robot_description"
    assert "rviz_default_plugins/TF" in displays
    assert rviz["Visualization Manager"]["Global Options"]["Fixed Frame"] == "camera"
    layout = json.loads((share / "body_scheme.foxglove.json").read_text())
    scene = layout["configById"]["3D!bodyscheme"]
    assert set(scene["topics"]) == {"/body_scheme/markers", "/body_scheme/poses", "/tf"}
    assert scene["followTf"] == "camera"
