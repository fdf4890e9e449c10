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
