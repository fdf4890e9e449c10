"""Shipped robot files and loading robots from a URDF plus a marker placement file."""

from __future__ import annotations

import pathlib

import numpy as np
import pybullet_data
import pytest

from body_scheme_core import world as synthetic_world
from body_scheme_sim.errors import RobotFileError
from body_scheme_sim.robots import (
    MARKER_CHANGES,
    ROBOTS_DIR,
    generate_robot_files,
    load_robot,
    robot_files,
    robot_names,
)
from body_scheme_sim.robots.__main__ import main as robots_main
from body_scheme_sim.world import SimWorld

KUKA_URDF = pathlib.Path(pybullet_data.getDataPath()) / "kuka_iiwa" / "model.urdf"
KUKA_MARKERS = """\
markers:
- {id: 10, link: lbr_iiwa_link_2, xyz: [0.0, 0.1, 0.1], rpy: [0.0, 0.0, 0.0], size: 0.08}
- {id: 11, link: lbr_iiwa_link_4, xyz: [0.0, 0.1, 0.1], rpy: [0.0, 0.0, 0.0], size: 0.08}
- {id: 12, link: lbr_iiwa_link_7, xyz: [0.0, 0.0, 0.1], size: 0.06}
"""


def test_shipped_files_equal_a_fresh_generation():
    """Every shipped URDF and marker file is exactly what the generator writes now."""
    for name in robot_names():
        urdf_text, markers_text = generate_robot_files(name)
        assert (ROBOTS_DIR / f"{name}.urdf").read_text(encoding="utf-8") == urdf_text, name
        assert (ROBOTS_DIR / f"{name}.markers.yaml").read_text(encoding="utf-8") == markers_text, name


def test_check_command_reports_stale_files(tmp_path, capsys):
    """``--check`` passes on the shipped files and fails on a directory with an edited file."""
    assert robots_main(["--check"]) == 0
    assert robots_main(["--write", "--dir", str(tmp_path)]) == 0
    assert robots_main(["--check", "--dir", str(tmp_path)]) == 0
    (tmp_path / "arm_4dof.urdf").write_text("<robot name='edited'/>")
    assert robots_main(["--check", "--dir", str(tmp_path)]) == 1
    assert "arm_4dof.urdf" in capsys.readouterr().out


@pytest.mark.parametrize("name", ["arm_4dof", "powercube_6dof"])
def test_shipped_3d_arms_equal_their_core_builders(name):
    """The 3D arms load with the core builder's joints and marker poses; only the base marker is larger."""
    loaded, built = load_robot(name), synthetic_world.__dict__[name]()
    assert loaded.action_joint_names == built.action_joint_names
    np.testing.assert_allclose(loaded.action_lower, built.action_lower)
    q = np.random.default_rng(0).uniform(built.action_lower, built.action_upper, size=(20, built.n_actions))
    for marker_id in built.marker_ids:
        np.testing.assert_allclose(loaded.marker_poses(q)[marker_id], built.marker_poses(q)[marker_id], atol=1e-12)
        expected_size = MARKER_CHANGES[name]["size"].get(marker_id, built.marker(marker_id).size)
        assert loaded.marker(marker_id).size == expected_size
    assert loaded.marker(1).size == 0.1


@pytest.mark.parametrize("name", ["planar_2dof", "arm_4dof", "powercube_6dof"])
def test_each_robot_loads_and_executes_within_limits(name):
    """A shipped robot loads into a world and every executed command lands within its joint limits."""
    rng = np.random.default_rng(0)
    with SimWorld(name) as world:
        span = world.action_upper - world.action_lower
        for _ in range(10):
            command = rng.uniform(world.action_lower - span, world.action_upper + span)
            q = world.execute(command)
            assert np.all(q >= world.action_lower) and np.all(q <= world.action_upper)
            np.testing.assert_allclose(q, np.clip(command, world.action_lower, world.action_upper))
            np.testing.assert_array_equal(world.joint_positions(), q)


def test_other_urdf_with_a_marker_file(tmp_path):
    """pybullet_data's KUKA iiwa works with a marker file: pybullet's link poses match the tree's kinematics."""
    markers = tmp_path / "kuka.markers.yaml"
    markers.write_text(KUKA_MARKERS)
    tree = load_robot(KUKA_URDF, markers)
    assert tree.n_actions == 7 and tree.marker_ids == (10, 11, 12)
    rng = np.random.default_rng(0)
    with SimWorld(KUKA_URDF, markers_path=markers) as world:
        for _ in range(5):
            q = world.execute(rng.uniform(world.action_lower, world.action_upper))
            expected = tree.link_poses(q)
            for link, pose in world.drawn_link_poses().items():
                np.testing.assert_allclose(pose, expected[link], atol=1e-5, err_msg=link)
        image = world.render()
        assert image.shape == (480, 640, 3) and image.dtype == np.uint8


def test_missing_or_unknown_robot_files_raise_clear_errors(tmp_path):
    """Unknown names, URDFs without a marker file and broken marker files name the problem."""
    with pytest.raises(RobotFileError, match="unknown robot 'nonsense'"):
        load_robot("nonsense")
    with pytest.raises(RobotFileError, match="no marker file"):
        robot_files(KUKA_URDF)
    broken = tmp_path / "broken.yaml"
    broken.write_text("markers:\n- {id: 1, link: no_such_link}\n")
    with pytest.raises(RobotFileError, match="no_such_link"):
        load_robot(KUKA_URDF, broken)
    with pytest.raises(RobotFileError, match="does not exist"):
        load_robot(tmp_path / "absent.urdf", broken)
