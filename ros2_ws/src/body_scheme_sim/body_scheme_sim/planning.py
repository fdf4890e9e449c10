"""Markers planned for any robot, and a camera that frames them: what a user needs before printing markers.

:func:`plan_markers` puts one marker on each rigid body of a URDF that moves (its links joined by fixed joints count
as one body), and one on the root, or on the links the user names. For each body it casts rays at every link of the
body from 14 directions in the link's frame (the faces and corners of a cube) to find points on the link's collision
surface, lays a plate of each size in :data:`MARKER_SIZES` flat on each point, facing out, lifted until it no longer
penetrates the robot, and scores each by the random collision-free postures in which the camera sees it (the
simulator's visibility test with a margin: in the image, large enough, facing the camera, not occluded). It then
picks one candidate per body so that the pair of markers seen together least often (a local model learns only from
postures in which the camera sees both of its markers) is seen together as often as possible (:func:`_choose`).

:func:`auto_camera` places the camera in front of the robot and above it (the direction of the default camera) at the
closest distance at which every marker (or link origin) over random postures projects inside the image.
"""

from __future__ import annotations

import math
import pathlib
from dataclasses import dataclass

import numpy as np
import pybullet
from scipy.spatial.transform import Rotation

from body_scheme_core.errors import InvalidInputError
from body_scheme_core.transforms import invert_transform
from body_scheme_core.world import KinematicTree, Marker, markers_to_yaml

from .camera import DEFAULT_EYE, DEFAULT_TARGET, Camera, look_at
from .markers import PLATE_THICKNESS, marker_corners, plate_side

__all__ = ["MARKER_SIZES", "ROOT_MARKER_SIZE", "hd_camera", "PlannedMarker", "moving_bodies", "plan_markers",
           "write_markers", "auto_camera", "parse_camera"]

#: Marker edge lengths tried, m (largest first: a bigger marker is seen farther and more often).
MARKER_SIZES = (0.08, 0.06, 0.05, 0.04, 0.03)
#: The root's marker may also be this big: the camera sees it from one viewpoint, so its error is a bias that no
#: number of samples averages out, and a bigger marker has a smaller one.
ROOT_MARKER_SIZE = 0.10
#: Among markers seen equally often, the one whose normal makes the angle nearest this with the line of sight wins:
#: seen squarely, a planar marker's pose is ambiguous (IPPE); seen obliquely, its depth is poor. It matters most for
#: the root's marker, which the camera sees from one viewpoint only, so its error never averages out.
PREFERRED_VIEW_ANGLE = math.radians(30.0)
#: A plate may be lifted this far off the surface (m) to clear curved geometry; farther, it is too small a fit.
MAX_LIFT = 0.015
#: Gap left between a plate and the surface, m.
STANDOFF = 0.002
#: Planning counts a marker as seen only with this margin over the simulator's visibility test: each edge at least
#: this many pixels, and facing the camera within this angle. The tracker decodes the markers that barely pass that
#: test (12 px, 70 deg) only now and then: on rendered images of a 7-joint arm such markers were decoded in 5-20 %
#: of the postures the test counted.
PLAN_MIN_PIXELS = 20.0
PLAN_MAX_VIEW_ANGLE = math.radians(60.0)
#: A body moved by a prismatic joint with a shorter stroke (m) gets no marker: at a camera's noise (10 mm, 3 sigma
#: 30 mm) a static model explains it as well, e.g. a gripper's 4 cm fingers.
MIN_PRISMATIC_STROKE = 0.1
def hd_camera(world2camera=None):
    """A 1280 x 960 camera with a 60 deg horizontal field of view, a common webcam's HD mode: what ``auto`` and
    ``--camera x y z r p y`` simulate. The simulator's default 640 x 480 camera, framing a whole 7-joint arm's
    workspace, sees 8 cm markers at under 20 pixels, too small for the tracker to decode reliably."""
    f = 640.0 / math.tan(math.radians(30.0))
    pose = {} if world2camera is None else {"world2camera": world2camera}
    return Camera(width=1280, height=960, fx=f, fy=f, cx=639.5, cy=479.5, **pose)


_DIRECTIONS = np.array([d for d in np.ndindex(3, 3, 3) if sum(abs(v - 1) for v in d) in (1, 3)], dtype=float) - 1.0
_DIRECTIONS /= np.linalg.norm(_DIRECTIONS, axis=1, keepdims=True)


@dataclass(frozen=True)
class PlannedMarker:
    """A planned marker and how well it is seen: ``visible`` is the fraction of sampled postures in which the camera
    sees it, ``together`` the fraction in which it sees it and the marker of the body above it (``visible`` for the
    root's)."""

    marker: Marker
    visible: float
    together: float


def moving_bodies(tree, links=None):
    """The links that carry one marker each: the root link and each child of a commanded joint (a mimic joint's
    child too), or ``links``. Returns ``{link: [links rigidly attached to it, itself first]}`` in tree order."""
    if links is not None:
        unknown = sorted(set(links) - set(tree.links))
        if unknown:
            raise InvalidInputError(f"links {unknown} are not links of the robot; links: {list(tree.links)}")
        return {link: [link] for link in tree.links if link in set(links)}
    bodies = {}
    owner = {}
    for link in tree.links:  # breadth-first: a parent comes first
        joint = tree.parent_joint(link)
        if joint is None or joint.action is not None:
            owner[link] = link
            bodies[link] = [link]
        else:
            owner[link] = owner[joint.parent]
            bodies[owner[link]].append(link)
    return bodies


def _frame(normal):
    """A rotation whose z axis is ``normal`` (x axis as horizontal as possible)."""
    z = normal / np.linalg.norm(normal)
    x = np.cross((0.0, 0.0, 1.0), z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross((0.0, 1.0, 0.0), z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _surface_points(world, tree, link, q0):
    """``[(link2point, link_normal)]``: where rays from 14 directions hit ``link`` in posture ``q0``."""
    pb, robot = world._pb, world._robot_id
    index = world._link_index[link]
    world2link = tree.link_poses(q0)[link]
    lo, hi = (np.array(v) for v in pb.getAABB(robot, index))
    if not np.all(hi - lo < 10.0):
        return []
    centre, reach = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo)) + 0.05
    directions = _DIRECTIONS @ world2link[:3, :3].T
    hits = pb.rayTestBatch((centre + reach * directions).tolist(), np.tile(centre, (len(directions), 1)).tolist())
    link2world = invert_transform(world2link)
    points = []
    for hit in hits:
        if hit[0] == robot and hit[1] == index:
            position, normal = np.array(hit[3]), np.array(hit[4])
            points.append((link2world[:3, :3] @ position + link2world[:3, 3], link2world[:3, :3] @ normal))
    return points


def _lifted(world, world2plate, size):
    """How far (m, at most :data:`MAX_LIFT`) a plate's back face must rise along its normal to clear the robot, or
    None."""
    pb = world._pb
    side = plate_side(size)
    shape = pb.createCollisionShape(pybullet.GEOM_BOX, halfExtents=(0.5 * side, 0.5 * side, 0.5 * PLATE_THICKNESS))
    plate = pb.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape)
    try:
        for lift in np.arange(STANDOFF, MAX_LIFT + 1e-9, 0.0025):
            pose = world2plate.copy()
            pose[:3, 3] += (lift + 0.5 * PLATE_THICKNESS) * pose[:3, 2]
            quaternion = _quaternion(pose[:3, :3])
            pb.resetBasePositionAndOrientation(plate, pose[:3, 3].tolist(), quaternion)
            pb.performCollisionDetection()
            if not pb.getClosestPoints(plate, world._robot_id, 0.0):
                return float(lift)
        return None
    finally:
        pb.removeBody(plate)


def _quaternion(R):
    return Rotation.from_matrix(R).as_quat().tolist()


def _postures(world, n, rng):
    """Up to ``n`` random postures within the limits in which the robot does not collide (at least the zero one)."""
    tree = world.nominal_robot
    found, saved = [], world.last_command
    for _ in range(20 * n):
        a = rng.uniform(tree.action_lower, tree.action_upper)
        world.execute(a)
        if not world.in_collision():
            found.append(world.joint_positions())
            if len(found) == n:
                break
    world.execute(saved)
    return found or [world.joint_positions()]


def _stands(world, tree, camera, size, world2root):
    """Root markers on a stand, for when the root's own surface is all too small or hidden (a base under the first
    link, far from a camera framing the whole arm): a plate of ``size`` on the ground beside the root link's
    geometry, at five bearings around the camera's, facing the camera, fixed to the root link: ``[(size, link,
    link2marker)]``."""
    pb = world._pb
    boxes = [pb.getAABB(world._robot_id, world._link_index[link]) for link in moving_bodies(tree)[tree.root_link]]
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    centre = 0.5 * (lo + hi)
    towards = camera.position - centre
    bearing = math.atan2(towards[1], towards[0])
    radius = 0.5 * float(np.linalg.norm((hi - lo)[:2])) + 0.05 + 0.5 * size
    candidates = []
    for turn in np.radians([0.0, 40.0, -40.0, 80.0, -80.0]):
        world2marker = np.eye(4)
        world2marker[:3, 3] = [centre[0] + radius * math.cos(bearing + turn),
                               centre[1] + radius * math.sin(bearing + turn), 0.6 * size + 0.01]
        # Tilted 25 deg up from the line of sight: a marker squarely facing the camera gives IPPE two equally good
        # poses, and the tracker rejects such ambiguous detections.
        sight = camera.position - world2marker[:3, 3]
        sight /= np.linalg.norm(sight)
        side = np.cross(sight, (0.0, 0.0, 1.0))
        world2marker[:3, :3] = _frame(Rotation.from_rotvec(math.radians(25.0) * side / np.linalg.norm(side))
                                      .apply(sight))
        candidates.append((size, tree.root_link, invert_transform(world2root) @ world2marker))
    return candidates


def _plates(world, tree, link, q0, sizes):
    """Plates on ``link``'s surface: at each point the rays find, the biggest of ``sizes`` that clears the robot,
    ``[(size, link, link2marker)]``."""
    plates = []
    for link2point, normal in _surface_points(world, tree, link, q0):
        for size in sorted(sizes, reverse=True):
            link2marker = np.eye(4)
            link2marker[:3, :3] = _frame(normal)
            link2marker[:3, 3] = link2point
            lift = _lifted(world, tree.link_poses(q0)[link] @ link2marker, size)
            if lift is not None:
                # The marker's frame is on the plate's front face: the checked plate spans [lift, lift + thickness].
                link2marker[:3, 3] += (lift + PLATE_THICKNESS) * link2marker[:3, 2]
                plates.append((size, link, link2marker))
                break  # the biggest plate that fits at this point
    return plates


def _view_angle(camera, world2markers):
    """Mean angle (rad) between the markers' normals and their lines of sight (pi/2 for none)."""
    if len(world2markers) == 0:
        return math.pi / 2
    sight = camera.position - world2markers[:, :3, 3]
    sight /= np.linalg.norm(sight, axis=1, keepdims=True)
    return float(np.mean(np.arccos(np.clip(np.einsum("ki,ki->k", sight, world2markers[:, :3, 2]), -1.0, 1.0))))


def _marked_parent(tree, body, marked):
    """The nearest link above ``body`` that is in ``marked`` (None for none)."""
    joint = tree.parent_joint(body)
    while joint is not None and joint.parent not in marked:
        joint = tree.parent_joint(joint.parent)
    return None if joint is None else joint.parent


def _choose(tree, candidates):
    """One candidate per body (``{body: candidate}`` in tree order) that maximises the bottleneck of the tree: the
    smallest fraction of postures in which a marker and the marker of the nearest marked body above it are seen
    together (a local model learns only from those; the scarcest pair sets how long learning takes). Dynamic
    programming from the leaves up: ``value(c)`` is the best bottleneck below candidate ``c``; then from the root
    down, each body takes the candidate with the best ``min(together with its parent, value)``, then the one seen
    most often, the bigger plate, the view angle nearest :data:`PREFERRED_VIEW_ANGLE`."""
    bodies = [link for link in tree.links if link in candidates]  # breadth-first: parents first
    parent = {body: _marked_parent(tree, body, candidates) for body in bodies}
    children = {body: [c for c in bodies if parent[c] == body] for body in bodies}
    seen = {body: np.array([c[0] for c in candidates[body]]) for body in bodies}  # (k, n_postures)
    together = {body: (seen[parent[body]].astype(float) @ seen[body].T.astype(float)) / seen[body].shape[1]
                for body in bodies if parent[body] is not None}  # (k_parent, k)
    value = {}
    for body in reversed(bodies):
        v = seen[body].mean(axis=1)
        for child in children[body]:
            v = np.minimum(v, np.max(np.minimum(together[child], value[child][None, :]), axis=1))
        value[body] = v

    def rank(body, k, score):
        c = candidates[body][k]
        return round(float(score), 2), round(float(c[0].mean()), 2), c[1], -abs(c[4] - PREFERRED_VIEW_ANGLE)

    chosen, index = {}, {}
    for body in bodies:
        if parent[body] is None:
            scores = value[body]
        else:
            scores = np.minimum(together[body][index[parent[body]]], value[body])
        index[body] = max(range(len(scores)), key=lambda k, b=body, sc=scores: rank(b, k, sc[k]))
        chosen[body] = candidates[body][index[body]]
    return chosen


def _visibility(world, camera, tree, postures, candidates):
    """Which candidates ``[(size, link, link2marker)]`` the camera sees in each posture, shape (k, n_postures): the
    simulator's test (in the image, facing the camera, large enough, rays from the camera unobstructed by the robot
    in that posture) with the margins :data:`PLAN_MIN_PIXELS` and :data:`PLAN_MAX_VIEW_ANGLE`."""
    seen = np.zeros((len(candidates), len(postures)), dtype=bool)
    if not candidates:
        return seen
    eye = camera.position
    links = tree.link_poses(np.asarray(postures))
    corners = {size: np.vstack([marker_corners(size), np.zeros(3)]) for size, _, _ in candidates}
    saved = world.last_command
    try:
        for k, q in enumerate(postures):
            world.execute(q)
            rays, owners = [], []
            for c, (size, link, link2marker) in enumerate(candidates):
                pose = links[link][k] @ link2marker
                to_camera = eye - pose[:3, 3]
                if not pose[:3, 2] @ to_camera > math.cos(PLAN_MAX_VIEW_ANGLE) * np.linalg.norm(to_camera):
                    continue
                points = corners[size] @ pose[:3, :3].T + pose[:3, 3]
                uv, depth = camera.project(points[:4])
                if not (np.all(depth > camera.near) and np.all(camera.in_image(uv, 2.0))):
                    continue
                if np.min(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)) < PLAN_MIN_PIXELS:
                    continue
                towards = points - eye
                rays.append(eye + towards * (1.0 - 0.002 / np.linalg.norm(towards, axis=1, keepdims=True)))
                owners.append(c)
            if not owners:
                continue
            targets = np.concatenate(rays)
            hits = world._pb.rayTestBatch(np.tile(eye, (len(targets), 1)).tolist(), targets.tolist())
            clear = np.array([hit[0] < 0 for hit in hits]).reshape(len(owners), -1).all(axis=1)
            seen[np.array(owners)[clear], k] = True
    finally:
        world.execute(saved)
    return seen


def plan_markers(urdf_path, camera=None, template=None, links=None, sizes=MARKER_SIZES, n_postures=120, seed=0,
                 package_path=(), first_id=1):
    """Plan one marker per moving body of a URDF robot (see the module docstring).

    Parameters
    ----------
    urdf_path : str or os.PathLike
    camera : Camera or None
        ``None``: :func:`auto_camera` framing the robot's links, with the intrinsics of ``template``.
    template : Camera or None
    links : iterable of str or None
        Links to put markers on; ``None``: :func:`moving_bodies`.
    sizes : iterable of float
        Marker edge lengths to try, m.
    n_postures : int
        Random collision-free postures the visibility is scored on.
    seed : int
    package_path : iterable of str
        See :class:`~body_scheme_sim.world.SimWorld`.
    first_id : int
        Marker ids are ``first_id, first_id + 1, ...`` in tree order (the root's first).

    Returns
    -------
    planned : list of PlannedMarker
        One per body that has a candidate seen at least once, in tree order.
    skipped : dict of str to str
        Bodies (their first link) without a marker, and why: no collision geometry or never in view, or moved by a
        prismatic joint of less than :data:`MIN_PRISMATIC_STROKE` (unless named in ``links``).
    camera : Camera
        ``camera``, or the one :func:`auto_camera` chose.
    """
    from .world import SimWorld

    rng = np.random.default_rng(seed)
    with SimWorld(urdf_path, camera=camera, markers=(), marker_texture=False,
                  package_path=package_path) as world:
        tree = world.nominal_robot
        if camera is None:
            world.camera = camera = auto_camera(world, rng=rng, template=template)
        postures = _postures(world, n_postures, rng)
        q0 = world.joint_positions()
        planned, skipped = [], {}
        world2links = tree.link_poses(np.array(postures))
        geometry = {}  # body -> [(size, link, link2marker)]
        for body, members in moving_bodies(tree, links).items():
            joint = tree.parent_joint(body)
            if links is None and joint is not None and joint.type == "prismatic" \
                    and joint.upper - joint.lower < MIN_PRISMATIC_STROKE:
                skipped[body] = (f"its joint {joint.name} moves it {1000 * (joint.upper - joint.lower):.0f} mm, "
                                 f"too little for a camera to tell from noise")
                continue
            tried = {*sizes, ROOT_MARKER_SIZE} if body == tree.root_link and links is None else set(sizes)
            geometry[body] = [c for link in members for c in _plates(world, tree, link, q0, tried)]
        seen = {body: _visibility(world, camera, tree, postures, found) for body, found in geometry.items()}
        root = tree.root_link
        if root in geometry and not seen[root].any():
            geometry[root] += _stands(world, tree, camera, max(*sizes, ROOT_MARKER_SIZE), world2links[root][0])
            seen[root] = _visibility(world, camera, tree, postures, geometry[root])
        candidates = {}  # body -> [(seen (n_postures,), size, link, link2marker, view angle)]
        for body, found in geometry.items():
            kept = []
            for c, (size, link, link2marker) in enumerate(found):
                if seen[body][c].any():
                    poses = (world2links[link] @ link2marker)[seen[body][c]]
                    kept.append((seen[body][c], size, link, link2marker, _view_angle(camera, poses)))
            if kept:
                candidates[body] = kept
            else:
                skipped[body] = "no surface point of it is seen by the camera in the sampled postures"
        chosen = _choose(tree, candidates)
        for body, (seen, size, link, link2marker, _) in chosen.items():
            above = chosen.get(_marked_parent(tree, body, chosen))
            marker = Marker(id=first_id + len(planned), link=link, link2marker=link2marker, size=size)
            together = seen if above is None else seen & above[0]
            planned.append(PlannedMarker(marker, float(seen.mean()), float(together.mean())))
    if len(planned) and planned[-1].marker.id >= 50:
        raise InvalidInputError(f"{len(planned)} markers from id {first_id}: the ArUco dictionary DICT_4X4_50 holds "
                                f"ids 0..49; name fewer links")
    return planned, skipped, camera


def _link_boxes(world):
    """``{link: (8, 4)}``: the corners of each link's collision bounding box in the posture the world is in, in the
    link's frame (homogeneous)."""
    tree, pb = world.nominal_robot, world._pb
    poses = tree.link_poses(world.joint_positions())
    boxes = {}
    for link, index in world._link_index.items():
        lo, hi = (np.array(v) for v in pb.getAABB(world._robot_id, index))
        if not np.all(hi - lo < 10.0):
            continue
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        boxes[link] = corners @ invert_transform(poses[link]).T
    return boxes


def auto_camera(world_or_tree, markers=None, n_postures=30, rng=None, direction=None, template=None):
    """A camera framing the robot: the closest camera along ``direction`` from the middle of every marker (or, without
    markers, the robot's geometry) over random postures that sees all of them, 5 % inside the image's border.

    Parameters
    ----------
    world_or_tree : SimWorld or KinematicTree
    markers : iterable of Marker or None
        ``None``: the tree's markers; without any, the corners of each link's collision geometry's bounding box (a
        SimWorld) or the link origins (a tree).
    n_postures : int
    rng : numpy.random.Generator or None
    direction : array-like, shape (3,) or None
        From the robot towards the camera (default: that of the default camera, in front and 40 deg above).
    template : Camera or None
        Intrinsics to keep (default: :func:`hd_camera`).

    Returns
    -------
    camera : Camera
    """
    tree = world_or_tree if isinstance(world_or_tree, KinematicTree) else world_or_tree.nominal_robot
    rng = np.random.default_rng(0) if rng is None else rng
    A = rng.uniform(tree.action_lower, tree.action_upper, size=(n_postures, tree.n_actions))
    markers = tree.markers if markers is None else tuple(markers)
    links = tree.link_poses(A)
    if markers:
        points = np.concatenate([(links[m.link] @ m.link2marker)[:, :3, 3] for m in markers])
    else:
        outline = {} if isinstance(world_or_tree, KinematicTree) else _link_boxes(world_or_tree)
        points = np.concatenate([(T @ np.vstack([np.eye(4)[:, 3:].T, outline.get(link, np.zeros((0, 4)))]).T)
                                 .transpose(0, 2, 1)[..., :3].reshape(-1, 3) for link, T in links.items()])
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    template = hd_camera() if template is None else template
    direction = np.subtract(DEFAULT_EYE, DEFAULT_TARGET) if direction is None else np.asarray(direction, float)
    direction = direction / np.linalg.norm(direction)

    def camera_at(distance):
        return Camera(width=template.width, height=template.height, fx=template.fx, fy=template.fy,
                      cx=template.cx, cy=template.cy, world2camera=look_at(centre + distance * direction, centre),
                      near=template.near, far=max(template.far, 2.0 * distance + 2.0))

    def frames(distance):
        camera = camera_at(distance)
        uv, depth = camera.project(points)
        margin = 0.05 * min(camera.width, camera.height)
        return bool(np.all(depth > camera.near) and np.all(camera.in_image(uv, margin)))

    near, far = 0.2, 0.2
    while not frames(far) and far < 50.0:
        near, far = far, 2.0 * far
    for _ in range(30):  # bisection on the closest distance that frames every point
        middle = 0.5 * (near + far)
        near, far = (near, middle) if frames(middle) else (middle, far)
    return camera_at(far)


def parse_camera(text):
    """``"x y z roll pitch yaw"`` (m, rad: the optical frame's pose in the world, URDF rpy) as a :func:`hd_camera`;
    ``"auto"`` and ``None`` give None (the caller frames the robot)."""
    from body_scheme_core.transforms import transform_from_xyz_rpy

    if text is None or text.strip() == "auto":
        return None
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise InvalidInputError(f"--camera takes 'x y z roll pitch yaw' (m, rad) or 'auto', got {text!r}")
    return hd_camera(transform_from_xyz_rpy(values[:3], values[3:]))


def write_markers(planned, path):
    """Write the planned markers as a marker placement file (:func:`~body_scheme_core.world.load_markers_yaml`)."""
    path = pathlib.Path(path)
    path.write_text(markers_to_yaml([p.marker for p in planned]), encoding="utf-8")
    return path
