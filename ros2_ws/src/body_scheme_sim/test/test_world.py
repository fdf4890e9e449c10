"""SimWorld: rendering of the markers, visibility, noise-model perception, collisions and faults."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import invert_transform, transform_from_rotvec, transform_from_xyz_rpy
from body_scheme_core.world import Body, Joint, KinematicTree, Marker, deform_limb
from body_scheme_sim import collisions
from body_scheme_sim.camera import Camera, look_at
from body_scheme_sim.markers import aruco_dictionary, marker_corners, plate_side
from body_scheme_sim.world import SimWorld

#: A powercube configuration where the base marker faces the camera, inside the image, but the arm hides it.
OCCLUDING = [0.47, 0.99, -1.3, 1.0, -0.35, -0.52]
CONFIGURATIONS = [np.zeros(6), [0.2, 0.3, -0.4, 0.5, 0.1, -0.3], [-0.3, -0.5, 0.6, -0.8, -0.4, 0.6],
                  [0.1, 0.6, 1.0, 0.9, -1.0, 1.2]]


@pytest.fixture(scope="module")
def world():
    """One powercube world for the read-only tests of this module (each test sets its own configuration)."""
    with SimWorld("powercube_6dof") as w:
        yield w


def folding_arm():
    """Three pitch links on a post: link 3 can fold back onto link 1 and the arm can reach the ground."""
    def offset(z):
        return transform_from_xyz_rpy((0.0, 0.0, z), (0.0, 0.0, 0.0))
    y = (0.0, 1.0, 0.0)
    joints = [Joint("j1", "revolute", "base", "l1", origin=offset(0.2), axis=y, lower=-1.5, upper=1.5, action=0),
              Joint("j2", "revolute", "l1", "l2", origin=offset(0.3), axis=y, lower=-3.0, upper=3.0, action=1),
              Joint("j3", "revolute", "l2", "l3", origin=offset(0.3), axis=y, lower=-3.0, upper=3.0, action=2)]
    facing = transform_from_xyz_rpy((0.05, 0.0, 0.1), (0.0, math.pi / 2, 0.0))
    joints.append(Joint("tip_joint", "fixed", "l3", "tip", origin=offset(0.3)))  # gives link 3 its bone
    return KinematicTree(joints, [Marker(1, "base", facing), Marker(2, "l3", facing, size=0.08)])


def world_corners(world, marker_id):
    """Corners (4, 3) of a marker's black square in the world, ArUco order."""
    pose = world.world_marker_poses()[marker_id]
    return marker_corners(world.robot.marker(marker_id).size) @ pose[:3, :3].T + pose[:3, 3]


def grey(image, uv):
    """Mean grey level of the 3x3 pixels around (u, v)."""
    u, v = (int(round(c)) for c in uv)
    return image[v - 1:v + 2, u - 1:u + 2].mean()


def test_ground_truth_is_forward_kinematics_in_the_camera_frame(world):
    """true_marker_poses = camera^-1 @ tree forward kinematics, and pybullet draws the links there too."""
    for a in CONFIGURATIONS:
        q = world.execute(a)
        truth = world.true_marker_poses()
        root2marker = world.robot.marker_poses(q)
        for marker_id in world.marker_ids:
            np.testing.assert_allclose(truth[marker_id], world.camera2root @ root2marker[marker_id], atol=1e-12)
        links = world.robot.link_poses(q)
        for link, pose in world.drawn_link_poses().items():
            np.testing.assert_allclose(pose, links[link], atol=1e-6, err_msg=link)


def test_markers_render_where_ground_truth_projects(world):
    """Each visible marker's black border is drawn at its projected corners, inside a white plate margin."""
    checked = 0
    signs = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]])
    for a in CONFIGURATIONS:
        world.execute(a)
        image = cv2.cvtColor(world.render(), cv2.COLOR_RGB2GRAY)
        for marker_id in world.visible_marker_ids():
            size = world.robot.marker(marker_id).size
            pose = world.world_marker_poses()[marker_id]
            # inside the black border cell at each corner; on the white margin beyond the middle of each edge
            # (neighbouring plates may cover some of the margin)
            inside = np.c_[0.4 * size * signs, np.zeros(4)]
            margin = np.c_[0.5 * (size + plate_side(size)) / 2 * np.array([[-1, 0], [1, 0], [0, 1], [0, -1]]),
                           np.zeros(4)]
            uv, _ = world.camera.project(np.vstack([inside, margin]) @ pose[:3, :3].T + pose[:3, 3])
            levels = np.array([grey(image, p) for p in uv])
            assert np.all(levels[:4] < 60), (a, marker_id, levels)
            assert np.sum(levels[4:] > 150) >= 2, (a, marker_id, levels)
            checked += 1
    assert checked >= 10


def test_aruco_detects_the_right_ids_with_corners_in_opencv_order(world):
    """cv2.aruco finds the visible markers by their ids; its corners 0..3 land on the true TL, TR, BR, BL."""
    detector = cv2.aruco.ArucoDetector(aruco_dictionary())
    n_visible = n_detected = 0
    for a in CONFIGURATIONS:
        world.execute(a)
        visible = world.visible_marker_ids()
        corners, ids, _ = detector.detectMarkers(world.render())
        ids = [] if ids is None else ids.ravel().tolist()
        assert set(ids) <= set(world.marker_ids)
        n_visible += len(visible)
        n_detected += len(visible & set(ids))
        for found, marker_id in zip(corners, ids, strict=True):
            uv, _ = world.camera.project(world_corners(world, marker_id))
            assert np.max(np.linalg.norm(found[0] - uv, axis=1)) < 2.0, marker_id
    assert n_detected >= 0.8 * n_visible and n_visible >= 10


def test_visibility_excludes_occluded_markers(world):
    """A marker facing the camera inside the image but hidden behind the arm is not visible, nor drawn."""
    world.execute(OCCLUDING)
    pose = world.world_marker_poses()[1]
    to_camera = world.camera.position - pose[:3, 3]
    assert pose[:3, 2] @ to_camera / np.linalg.norm(to_camera) > 0.6
    uv, depth = world.camera.project(world_corners(world, 1))
    assert np.all(world.camera.in_image(uv, margin=20)) and np.all(depth > 0)
    assert 1 not in world.visible_marker_ids()
    image = cv2.cvtColor(world.render(), cv2.COLOR_RGB2GRAY)
    inside, _ = world.camera.project((pose @ [-0.4 * 0.08, 0.4 * 0.08, 0.0, 1.0])[None, :3])
    assert grey(image, inside[0]) > 60  # something else is drawn over the black border
    world.execute(np.zeros(6))
    assert 1 in world.visible_marker_ids()


def test_visibility_excludes_markers_facing_away_and_out_of_view():
    """Markers turned away from the camera, or outside a narrow camera's image, are not visible."""
    with SimWorld("powercube_6dof") as w:
        w.execute([0.0, 0.3, 0.0, 0.3, 0.0, 0.0])  # leaning towards the camera (upright, the tool is above the image)
        assert w.visible_marker_ids() == set(w.marker_ids)
        w.execute([1.5, 0.3, 0.0, 0.3, 0.0, 0.0])  # markers 2-7 turned 86 deg to the side
        assert w.visible_marker_ids() == {1}
    narrow = Camera(fx=1400.0, fy=1400.0, world2camera=look_at((1.55, 0.0, 1.7), (0.0, 0.0, 0.1)))
    with SimWorld("powercube_6dof", camera=narrow) as w:
        uv, _ = w.camera.project(np.array([p[:3, 3] for p in w.world_marker_poses().values()]))
        out_of_view = {i for i, ok in zip(w.marker_ids, w.camera.in_image(uv), strict=True) if not ok}
        assert len(out_of_view) >= 2
        visible = w.visible_marker_ids()
        assert 1 in visible and not visible & out_of_view


def test_noise_mode_statistics(world):
    """observe_noisy has the configured 3D RMS errors, drops markers at 1 - visibility, never shows hidden ones."""
    world.execute(CONFIGURATIONS[1])
    visible = world.visible_marker_ids()
    assert 3 <= len(visible) < len(world.marker_ids)
    truth = world.true_marker_poses()
    rng = np.random.default_rng(0)
    errors_t, errors_r, seen = [], [], []
    for _ in range(1000):
        observed = world.observe_noisy(sigma_trans=0.044, sigma_rot=0.2, visibility=0.7, rng=rng)
        assert set(observed) <= visible
        seen.append(len(observed))
        for marker_id, pose in observed.items():
            errors_t.append(np.linalg.norm(pose[:3, 3] - truth[marker_id][:3, 3]))
            delta = truth[marker_id][:3, :3].T @ pose[:3, :3]
            errors_r.append(Rotation.from_matrix(delta).magnitude())
    assert np.sqrt(np.mean(np.square(errors_t))) == pytest.approx(0.044, rel=0.05)
    assert np.sqrt(np.mean(np.square(errors_r))) == pytest.approx(0.2, rel=0.05)
    assert np.mean(seen) / len(visible) == pytest.approx(0.7, abs=0.03)


def test_noise_mode_is_reproducible_with_a_seed():
    """Two worlds with the same seed give identical noisy observations."""
    results = []
    for _ in range(2):
        with SimWorld("arm_4dof", seed=3, marker_texture=False) as w:
            results.append([w.observe_noisy() for _ in range(5)])
    for first, second in zip(*results, strict=True):
        assert first.keys() == second.keys()
        for marker_id in first:
            np.testing.assert_array_equal(first[marker_id], second[marker_id])


def test_collisions_with_itself_and_the_ground():
    """Folding link 3 onto link 1 or pitching into the ground collides; the base on the ground does not."""
    with SimWorld(folding_arm()) as w:
        for q, expected in [((0.0, 0.0, 0.0), False), ((0.5, 0.5, 0.5), False), ((0.0, 2.8, 2.8), True),
                            ((1.0, 1.5, 0.0), True), ((-1.0, -1.5, 0.0), True)]:
            w.execute(q)
            assert w.in_collision() == expected, q


def test_worlds_in_one_process_are_independent():
    """Two worlds with their own pybullet clients do not see each other's robot or commands."""
    with SimWorld("arm_4dof") as first, SimWorld("planar_2dof") as second:
        before = second.true_marker_poses()
        image = second.render()
        first.execute([1.0, 0.5, -0.5, 0.3])
        for marker_id, pose in second.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])
        np.testing.assert_array_equal(second.render(), image)
        assert first.marker_ids == (1, 2, 3, 4, 5) and second.marker_ids == (1, 2, 3)


def test_block_joint_holds_its_angle_and_repair_restores_exactly():
    """A blocked joint ignores commands (only markers beyond it move); repair gives back the exact poses."""
    a = np.array([0.2, 0.3, -0.4, 0.5, 0.1, -0.3])
    with SimWorld("powercube_6dof", marker_texture=False) as w:
        w.execute(a)
        before = w.true_marker_poses()
        w.block_joint(5, 0.8)
        w.execute(a)
        assert w.joint_positions()[5] == 0.8
        after = w.true_marker_poses()
        expected = w.camera2root @ w.robot.marker_poses(np.r_[a[:5], 0.8])[7]
        np.testing.assert_allclose(after[7], expected, atol=1e-12)
        for marker_id in range(1, 7):
            np.testing.assert_array_equal(after[marker_id], before[marker_id])
        w.block_joint(2)  # None: stays where it is
        w.execute(np.zeros(6))
        np.testing.assert_array_equal(w.joint_positions()[[2, 5]], [-0.4, 0.8])
        assert [f.kind for f in w.faults] == ["block_joint", "block_joint"]
        w.repair()
        w.execute(a)
        assert w.faults == []
        for marker_id, pose in w.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])


def test_deform_limb_reloads_the_robot_and_repair_restores_exactly():
    """A bent, longer limb moves the markers beyond it as the core's deform_limb says, in pybullet too."""
    a = np.array([0.1, 0.2, 0.3, -0.4, 0.5, 0.6])
    with SimWorld("powercube_6dof") as w:
        w.execute(a)
        before, drawn_before = w.true_marker_poses(), w.drawn_link_poses()
        w.deform_limb("joint6", delta_length=0.1, delta_rotvec=(0.785, 0.0, 0.0))
        expected = deform_limb(Body(w.nominal_robot), "joint6", 0.1, (0.785, 0.0, 0.0)).tree
        after = w.true_marker_poses()
        np.testing.assert_allclose(after[7], w.camera2root @ expected.marker_poses(a)[7], atol=1e-12)
        assert np.linalg.norm(after[7][:3, 3] - before[7][:3, 3]) > 0.1
        for marker_id in range(1, 7):
            np.testing.assert_array_equal(after[marker_id], before[marker_id])
        links = expected.link_poses(a)
        for link, pose in w.drawn_link_poses().items():
            np.testing.assert_allclose(pose, links[link], atol=1e-6, err_msg=link)
        w.repair("deform_limb")
        for marker_id, pose in w.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])
        for link, pose in w.drawn_link_poses().items():
            np.testing.assert_allclose(pose, drawn_before[link], atol=1e-9)


def test_displace_marker_moves_only_that_marker_and_repair_restores_exactly():
    """A displaced marker's pose is the old one times delta; repairing one kind keeps the other faults."""
    delta = transform_from_rotvec([0.0, 0.0, 0.3], [0.05, 0.0, 0.0])
    with SimWorld("powercube_6dof", marker_texture=False) as w:
        w.execute([0.3, 0.1, 0.0, 0.2, 0.0, 0.1])
        before = w.true_marker_poses()
        w.displace_marker(7, delta)
        w.block_joint(0, 0.5)
        w.repair("block_joint")
        after = w.true_marker_poses()
        np.testing.assert_allclose(after[7], before[7] @ delta, atol=1e-12)
        np.testing.assert_allclose(invert_transform(before[7]) @ after[7], delta, atol=1e-12)
        for marker_id in range(1, 7):
            np.testing.assert_array_equal(after[marker_id], before[marker_id])
        assert [f.kind for f in w.faults] == ["displace_marker"]
        w.repair("displace_marker")
        np.testing.assert_array_equal(w.true_marker_poses()[7], before[7])


def test_faults_deform_an_external_urdf_keeping_its_meshes(tmp_path):
    """Deforming pybullet_data's KUKA patches its joint origins; its visuals stay meshes, and FK agrees."""
    import pybullet_data

    urdf = f"{pybullet_data.getDataPath()}/kuka_iiwa/model.urdf"
    markers = tmp_path / "kuka.markers.yaml"
    markers.write_text("markers:\n- {id: 3, link: lbr_iiwa_link_7, xyz: [0.0, 0.0, 0.1], size: 0.06}\n")
    with SimWorld(urdf, markers_path=markers) as w:
        q = w.execute(np.full(7, 0.3))
        w.deform_limb("lbr_iiwa_joint_4", delta_length=0.05, delta_rotvec=(0.0, 0.3, 0.0))
        links = w.robot.link_poses(q)
        for link, pose in w.drawn_link_poses().items():
            np.testing.assert_allclose(pose, links[link], atol=1e-5, err_msg=link)
        shapes = w._pb.getVisualShapeData(w._robot_id)
        assert any(shape[4].endswith(b".obj") or shape[4].endswith(b".stl") for shape in shapes)


def test_invalid_commands_and_faults_raise_and_change_nothing():
    """Wrong shapes, NaN, out-of-range indices or angles and unknown names are refused before any change."""
    with SimWorld("arm_4dof", marker_texture=False) as w:
        before = w.true_marker_poses()
        for bad in ([0.0, 0.0], [0.0, np.nan, 0.0, 0.0]):
            with pytest.raises(InvalidInputError):
                w.execute(bad)
        with pytest.raises(InvalidInputError, match="action_index"):
            w.block_joint(4, 0.0)
        with pytest.raises(InvalidInputError, match="outside"):
            w.block_joint(0, 5.0)
        with pytest.raises(InvalidInputError, match="neither a joint nor a link"):
            w.deform_limb("elbow", 0.1)
        with pytest.raises(InvalidInputError, match="unknown marker id"):
            w.displace_marker(42, np.eye(4))
        with pytest.raises(InvalidInputError, match="repair kind"):
            w.repair("everything")
        assert w.faults == []
        for marker_id, pose in w.true_marker_poses().items():
            np.testing.assert_array_equal(pose, before[marker_id])


def test_marker_ids_outside_the_aruco_dictionary_are_refused_for_textures():
    """A marker id without an ArUco pattern fails with a clear message when textures are drawn."""
    tree = KinematicTree(folding_arm().joints, [Marker(77, "l3")])
    with pytest.raises(InvalidInputError, match="DICT_4X4_50"):
        SimWorld(tree)
    with SimWorld(tree, marker_texture=False) as w:
        assert w.marker_ids == (77,)


def test_render_gives_an_rgb_image_of_the_camera_size():
    """render() returns (height, width, 3) uint8 for a non-default camera."""
    with SimWorld("planar_2dof", camera=Camera(width=320, height=240, fx=280.0, fy=280.0, cx=160.0, cy=120.0)) as w:
        image = w.render()
        assert image.shape == (240, 320, 3) and image.dtype == np.uint8
        assert image.std() > 10  # not blank


def test_creating_worlds_prints_no_argv_line():
    """pybullet's C code prints a bare ``argv[0]=`` for every client; our worlds and renderings print nothing."""
    import subprocess
    import sys

    code = ("from body_scheme_sim.world import SimWorld\n"
            "world = SimWorld('planar_2dof')\nworld.render()\nSimWorld('planar_2dof').close()\nprint('done')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "argv[0]=" not in out.stdout and "done" in out.stdout, out.stdout


def test_a_urdf_whose_meshes_are_missing_still_loads_for_its_kinematics(tmp_path):
    """Meshes that cannot be found are listed once and left out of the drawing; the robot moves and its markers'
    ground truth follows the URDF's kinematics."""
    mesh = '<collision><geometry><mesh filename="package://nope/m.stl"/></geometry></collision>'
    urdf = tmp_path / "r.urdf"
    urdf.write_text(f'<robot name="r"><link name="a">{mesh}</link><link name="b">{mesh}<visual><geometry><mesh '
                    f'filename="package://nope/m.stl"/></geometry></visual></link><joint name="j" type="revolute">'
                    f'<parent link="a"/><child link="b"/><origin xyz="0 0 0.5"/><axis xyz="0 0 1"/><limit '
                    f'lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    with SimWorld(urdf, markers=[Marker(1, "a"), Marker(2, "b")], marker_texture=False) as world:
        assert world.missing_meshes == ["package://nope/m.stl"]
        world.execute([0.7])
        truth = world.world_marker_poses()
        np.testing.assert_allclose(truth[2][:3, 3], [0.0, 0.0, 0.5], atol=1e-12)
        np.testing.assert_allclose(truth[2][:3, :3], world.robot.link_poses([0.7])["b"][:3, :3], atol=1e-12)


COVER_URDF = """<robot name="covered">
  <link name="base"><collision><origin xyz="0 0 0.3"/><geometry><box size="0.2 0.2 0.6"/></geometry></collision>
    <inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="turntable"><inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/>
    </inertial></link>
  <link name="slider"><collision><origin xyz="0 0 -0.34"/><geometry><sphere radius="0.05"/></geometry></collision>
    <inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="probe"><collision><origin xyz="0.4 0 0"/><geometry><sphere radius="0.05"/></geometry></collision>
    <inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="turn" type="revolute"><parent link="base"/><child link="turntable"/><origin xyz="0 0 1.0"/>
    <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="slide" type="prismatic"><parent link="turntable"/><child link="slider"/><axis xyz="0 0 -1"/>
    <limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="swing" type="revolute"><parent link="turntable"/><child link="probe"/><origin xyz="0 0 -0.3"/>
    <axis xyz="0 1 0"/><limit lower="-1.5" upper="1.5" effort="1" velocity="1"/></joint>
</robot>
"""


def test_links_that_touch_in_almost_every_posture_are_not_checked_and_the_others_are(tmp_path):
    """MoveIt's "always in collision": the slider's sphere sinks into the base's cover as soon as it leaves 0 (98 % of
    its range), so checking that pair would refuse almost every command; the probe still hits the base when it
    swings down to it, and that is a collision."""
    path = tmp_path / "covered.urdf"
    path.write_text(COVER_URDF)
    with SimWorld(path, markers=(), marker_texture=False) as world:
        assert ("base", "slider") in world.ignored_collision_pairs
        assert not any("probe" in pair for pair in world.ignored_collision_pairs)
        world.execute([0.0, 0.1, 0.0])  # the slider in the cover, the probe level
        assert not world.in_collision()
        world.execute([0.0, 0.1, 1.4])  # the probe swung down into the cover, high above the ground
        assert world.in_collision()
        world.execute([0.0, 0.0, 0.0])
        assert not world.in_collision()


def test_a_second_world_of_the_same_robot_reuses_the_sampled_pairs(tmp_path, monkeypatch):
    monkeypatch.setattr(collisions, "_ALWAYS_IN_CONTACT", {})  # not what another test's world left
    path = tmp_path / "covered.urdf"
    path.write_text(COVER_URDF)
    screened = []
    pairs_in_contact = SimWorld._pairs_in_contact

    def counted(world):
        screened.append(1)
        return pairs_in_contact(world)

    monkeypatch.setattr(SimWorld, "_pairs_in_contact", counted)
    with SimWorld(path, markers=(), marker_texture=False) as world:
        first = world.ignored_collision_pairs
    assert len(screened) == 1 + collisions.ALWAYS_SAMPLES  # the reference posture, then the samples
    screened.clear()
    with SimWorld(path, markers=(), marker_texture=False) as world:
        assert world.ignored_collision_pairs == first
    assert len(screened) == 1  # the reference posture only
    screened.clear()
    path.write_text(COVER_URDF.replace('upper="0.5"', 'upper="0.4"'))  # another robot: sampled
    SimWorld(path, markers=(), marker_texture=False).close()
    assert len(screened) == 1 + collisions.ALWAYS_SAMPLES


def test_a_flat_plate_of_tags_is_drawn_as_one_piece_and_tracked_as_one_pose():
    """A 2 x 2 plate of 3 cm tags 2 cm apart (one ``plate`` key) on the base, seen obliquely from 0.6 m: drawn as the
    sheet prints it, one white piece (white between the tags, where tags on plates of their own showed the ground),
    every tag detected with its id, and the tracker, told the plate, puts it where the ground truth is (2 mm, 1 deg)."""
    from body_scheme_core.perception import MarkerTracker
    from body_scheme_core.plates import plates_from_markers

    facing = transform_from_xyz_rpy((0.05, 0.0, 0.1), (0.0, math.pi / 2, 0.0))
    markers = []
    for k, tag_id in enumerate((20, 21, 22, 23)):
        on_plate = transform_from_xyz_rpy(((k % 2) * 0.05, -(k // 2) * 0.05, 0.0), (0.0, 0.0, 0.0))
        markers.append(Marker(tag_id, "base", facing @ on_plate, size=0.03, plate=20))
    tree = KinematicTree(folding_arm().joints, markers)
    camera = Camera(world2camera=look_at((0.5, 0.3, 0.3), (0.05, 0.02, 0.08)))
    with SimWorld(tree, camera=camera) as w:
        image = cv2.cvtColor(w.render(), cv2.COLOR_RGB2GRAY)
        between = (facing @ transform_from_xyz_rpy((0.025, 0.0, 0.0), (0.0, 0.0, 0.0)))[:3, 3]  # tags 20 and 21
        uv, _ = camera.project(between[None])
        assert grey(image, uv[0]) > 200
        _, ids, _ = cv2.aruco.ArucoDetector(aruco_dictionary()).detectMarkers(image)
        assert sorted(np.ravel(ids).tolist()) == [20, 21, 22, 23]
        tracker = MarkerTracker(camera.K, marker_sizes=0.03, plates=plates_from_markers(markers))
        poses, rejected = tracker.detect(image)
        truth = w.true_marker_poses()[20]
        assert set(poses) == {20} and rejected == []
        assert np.linalg.norm(poses[20][:3, 3] - truth[:3, 3]) < 0.002
        angle = Rotation.from_matrix(poses[20][:3, :3].T @ truth[:3, :3]).magnitude()
        assert angle < math.radians(1.0)
