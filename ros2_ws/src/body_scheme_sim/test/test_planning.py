"""Markers planned on real robots' URDFs (pybullet_data), and the camera that frames them."""

import math
import pathlib

import numpy as np
import pybullet_data
import pytest
import yaml

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import transform_from_xyz_rpy
from body_scheme_sim.camera import camera_parameters, read_camera, write_camera
from body_scheme_sim.markers import beside_markers
from body_scheme_sim.planning import auto_camera, hd_camera, moving_bodies, parse_camera, plan_markers
from body_scheme_sim.robots import load_robot
from body_scheme_sim.world import SimWorld

DATA = pathlib.Path(pybullet_data.getDataPath())
PANDA, XARM = DATA / "franka_panda" / "panda.urdf", DATA / "xarm" / "xarm6_robot.urdf"


@pytest.fixture(scope="module")
def panda_plan():
    return plan_markers(PANDA, n_postures=60)


def test_one_marker_per_moving_body_of_the_panda_and_none_on_its_fingers(panda_plan):
    """The root and each of the seven links get one marker (ids 1..8 in tree order, on a link of that body); the
    mimic fingers' 4 cm stroke gets none, and the reason says so."""
    planned, skipped, _ = panda_plan
    assert [p.marker.id for p in planned] == list(range(1, 9))
    bodies = moving_bodies(load_robot(PANDA, markers=()))
    assert list(bodies) == ["panda_link0"] + [f"panda_link{k}" for k in range(1, 8)] + ["panda_leftfinger",
                                                                                          "panda_rightfinger"]
    assert "panda_hand" in bodies["panda_link7"]  # rigidly attached through fixed joints: one body
    for plan, members in zip(planned, list(bodies.values())[:8], strict=True):
        assert plan.marker.link in members
    assert set(skipped) == {"panda_leftfinger", "panda_rightfinger"}
    assert all("40 mm" in why for why in skipped.values())
    assert planned[0].visible > 0.8 and all(p.visible >= p.together > 0.05 for p in planned)


def test_planned_plates_sit_outside_the_robot_and_the_camera_sees_them(panda_plan):
    """In the simulator with the planned markers: no plate penetrates the robot in the reference posture, and over
    random collision-free postures every marker is seen at least once (the simulator's own visibility test)."""
    planned, _, camera = panda_plan
    with SimWorld(PANDA, camera=camera, markers=[p.marker for p in planned], marker_texture=False) as world:
        pb = world._pb
        pb.performCollisionDetection()
        for marker_id, (body, _) in world._marker_bodies.items():
            deepest = min((c[8] for c in pb.getClosestPoints(body, world._robot_id, 0.0)), default=0.0)
            assert deepest > -1e-4, (marker_id, deepest)
        seen, rng = set(), np.random.default_rng(1)
        for _ in range(150):
            world.execute(rng.uniform(world.action_lower, world.action_upper))
            if not world.in_collision():
                seen |= world.visible_marker_ids()
        assert seen == {p.marker.id for p in planned}


def test_the_base_gets_a_marker_and_named_links_get_theirs():
    """The xarm's base sits under its first link: its marker is planned all the same (on the base or, were it
    hidden, on a stand beside it); with ``links`` only the named links get one."""
    planned, skipped, _ = plan_markers(XARM, n_postures=40)
    assert planned[0].marker.link in ("world", "link_base") and planned[0].visible > 0.8 and not skipped
    named, _, _ = plan_markers(XARM, links=["link2", "link4"], n_postures=40)
    assert [p.marker.link for p in named] == ["link2", "link4"]
    with pytest.raises(InvalidInputError, match="not links"):
        plan_markers(XARM, links=["nope"])


def test_the_auto_camera_frames_every_marker():
    """Over random postures other than those the camera was fitted on, every planned marker projects inside the
    image, in front of the camera."""
    planned, _, _ = plan_markers(XARM, n_postures=40)
    tree = load_robot(XARM, markers=[p.marker for p in planned])
    camera = auto_camera(tree, rng=np.random.default_rng(3))
    A = np.random.default_rng(4).uniform(tree.action_lower, tree.action_upper, size=(30, tree.n_actions))
    links = tree.link_poses(A)
    points = np.concatenate([(links[m.link] @ m.link2marker)[:, :3, 3] for m in tree.markers])
    uv, depth = camera.project(points)
    assert np.all(depth > 0) and np.all(camera.in_image(uv))


def test_camera_option():
    assert parse_camera("auto") is None and parse_camera(None) is None
    camera = parse_camera("1 2 3 0 0 0")
    np.testing.assert_allclose(camera.position, [1, 2, 3])
    assert camera.width == 1280
    with pytest.raises(InvalidInputError, match="x y z roll pitch yaw"):
        parse_camera("1 2")
    with pytest.raises(InvalidInputError, match="x y z roll pitch yaw"):
        parse_camera(f"1 2 3 0 0 {math.inf}")


def test_a_root_without_geometry_in_view_gets_a_marker_on_a_stand(tmp_path):
    """A root link with nothing to stick a marker on gets one on a stand beside it, fixed to it."""
    urdf = tmp_path / "stick.urdf"
    urdf.write_text('<robot name="stick"><link name="base"/><link name="arm"><collision><origin xyz="0 0 0.3"/>'
                    '<geometry><box size="0.12 0.12 0.6"/></geometry></collision></link><joint name="j" '
                    'type="revolute"><parent link="base"/><child link="arm"/><origin xyz="0 0 0.05"/><axis '
                    'xyz="0 1 0"/><limit lower="-0.8" upper="0.8" effort="1" velocity="1"/></joint></robot>')
    planned, skipped, camera = plan_markers(urdf, n_postures=30)
    assert [p.marker.link for p in planned] == ["base", "arm"] and not skipped
    stand = planned[0]
    assert stand.visible > 0.3 and stand.marker.link2marker[2, 3] > 0.0  # above the ground (the arm hides it at times)
    to_camera = camera.position - stand.marker.link2marker[:3, 3]
    angle = math.degrees(math.acos(stand.marker.link2marker[:3, 2] @ to_camera / np.linalg.norm(to_camera)))
    assert 15.0 < angle < 35.0  # tilted away from the line of sight: not the ambiguous square-on view


def test_the_plans_camera_file_round_trips_and_a_broken_one_is_one_line_naming_it(tmp_path):
    camera = hd_camera(transform_from_xyz_rpy([1.5, -0.2, 1.1], [-2.0, 0.1, 1.4]))
    path = write_camera(camera, beside_markers(tmp_path / "run.markers.yaml", "camera.yaml"))
    assert path == tmp_path / "run.camera.yaml"
    back = read_camera(path)
    assert (back.width, back.height, back.fx, back.fy, back.cx, back.cy) == \
        (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
    assert np.allclose(back.world2camera, camera.world2camera, atol=1e-12)
    assert yaml.safe_load(path.read_text()) == camera_parameters(camera)  # sim_node's camera.* parameters
    broken = {"missing.yaml": None, "not_yaml.yaml": "camera: [", "no_key.yaml": "camera: {width: 640}",
              "short.yaml": yaml.safe_dump({"camera": {**camera_parameters(camera)["camera"], "xyz": [1.0, 2.0]}})}
    for name, text in broken.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(InvalidInputError, match=f"camera file {tmp_path / name}: ") as error:
            read_camera(tmp_path / name)
        assert "\n" not in str(error.value), name
