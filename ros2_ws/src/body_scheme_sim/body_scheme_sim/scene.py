"""The pybullet scene of the simulated world: a headless client, the ground, the marker plates, the robot's URDF with
a faulty body's joint origins, its link poses as pybullet holds them, and the TinyRenderer images.

:class:`~body_scheme_sim.world.SimWorld` builds its scene from these pieces; they hold no state of their own.
"""

from __future__ import annotations

import os
import sys
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pybullet
from pybullet_utils.bullet_client import BulletClient
from scipy.spatial.transform import Rotation

from body_scheme_core.transforms import xyz_rpy_from_transform
from body_scheme_core.world import resolve_meshes

from .markers import MARKER_CELLS, PLATE_THICKNESS, write_plate_obj
from .sheet import pieces, plate_face

__all__ = ["direct_client", "create_ground", "create_marker_plates", "render", "render_ground", "patched_urdf",
           "link_poses"]

# Collision filter group of the marker plates: rays hit them, the robot and the ground never collide with them.
_MARKER_GROUP = 2
_GROUND_HALF_SIZE = 1.4  # m; the floor ends behind the robot (a white wall beyond)
_GROUND_RGBA = (0.55, 0.6, 0.5, 1.0)
_PLAIN_PLATE_RGBA = (0.9, 0.9, 0.9, 1.0)
_PIXELS_PER_CELL = 16  # texture resolution of the smallest marker of a plate


def direct_client():
    """A pybullet ``DIRECT`` client, without the bare ``argv[0]=`` line pybullet's C code prints on stdout."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            return BulletClient(connection_mode=pybullet.DIRECT)
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def create_ground(pb):
    """The ground plane ``z = 0`` for collisions and lines of sight (drawn by :func:`render_ground`); its body id."""
    # A body without a visual shape would be drawn from its collision shape (an endless plane); give it an
    # invisible speck instead.
    speck = pb.createVisualShape(pybullet.GEOM_SPHERE, radius=1e-4, rgbaColor=(0.0, 0.0, 0.0, 0.0),
                                 visualFramePosition=(0.0, 0.0, -1.0))
    return pb.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=pb.createCollisionShape(pybullet.GEOM_PLANE),
                              baseVisualShapeIndex=speck)


def create_marker_plates(pb, directory, markers, textured):
    """One textured plate body per piece of :func:`.sheet.pieces` (a marker, or a flat plate of several tags drawn
    as printed), its files in ``directory``; ``{id of the marker or plate: (body, marker2body)}``."""
    obj_path = str(write_plate_obj(directory))
    bodies = {}
    for piece_id, members, centres in pieces(markers):
        pixels_per_m = _PIXELS_PER_CELL * MARKER_CELLS / min(m.size for m in members)
        face, _, (cx, cy) = plate_face(members, centres, pixels_per_m, patterns=textured)
        width, height = face.shape[1] / pixels_per_m, face.shape[0] / pixels_per_m
        visual = pb.createVisualShape(pybullet.GEOM_MESH, fileName=obj_path,
                                      meshScale=(width, height, PLATE_THICKNESS),
                                      rgbaColor=(1.0, 1.0, 1.0, 1.0) if textured else _PLAIN_PLATE_RGBA)
        shape = pb.createCollisionShape(pybullet.GEOM_BOX, halfExtents=(0.5 * width, 0.5 * height,
                                                                        0.5 * PLATE_THICKNESS),
                                        collisionFramePosition=(0.0, 0.0, -0.5 * PLATE_THICKNESS))
        body = pb.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape, baseVisualShapeIndex=visual)
        pb.setCollisionFilterGroupMask(body, -1, _MARKER_GROUP, 0)
        if textured:
            texture_path = directory / f"aruco_{piece_id}.png"
            cv2.imwrite(str(texture_path), cv2.cvtColor(face, cv2.COLOR_GRAY2BGR))
            pb.changeVisualShape(body, -1, textureUniqueId=pb.loadTexture(str(texture_path)))
        marker2body = np.eye(4)
        marker2body[:2, 3] = (cx, cy)
        bodies[piece_id] = (body, marker2body)
    return bodies


def render(pb, camera):
    """Colour (height, width, 3) uint8 and depth-buffer (height, width) float images of a pybullet scene."""
    light = camera.position / max(np.linalg.norm(camera.position), 1e-9)
    _, _, rgba, depth, _ = pb.getCameraImage(
        camera.width, camera.height, viewMatrix=camera.view_matrix, projectionMatrix=camera.projection_matrix,
        renderer=pybullet.ER_TINY_RENDERER, flags=pybullet.ER_NO_SEGMENTATION_MASK, shadow=0,
        lightDirection=light, lightAmbientCoeff=0.6, lightDiffuseCoeff=0.4, lightSpecularCoeff=0.0)
    shape = (camera.height, camera.width)
    rgb = np.asarray(rgba, dtype=np.uint8).reshape(*shape, 4)[..., :3]
    return rgb, np.asarray(depth, dtype=np.float32).reshape(shape)


def render_ground(camera):
    """:func:`render` of the ground alone (a square floor in a scene of its own): the backdrop of every frame."""
    scene = direct_client()
    try:
        half = _GROUND_HALF_SIZE
        visual = scene.createVisualShape(pybullet.GEOM_BOX, halfExtents=(half, half, 0.0005),
                                         visualFramePosition=(0.0, 0.0, -0.0005), rgbaColor=_GROUND_RGBA)
        scene.createMultiBody(baseMass=0.0, baseVisualShapeIndex=visual)
        return render(scene, camera)
    finally:
        scene.disconnect()


def patched_urdf(urdf_text, urdf_dir, tree, package_path=()):
    """URDF text with every joint's ``<origin>`` set from ``tree`` and its meshes resolved (``resolve_meshes``);
    returns ``(text, missing mesh URIs)``."""
    root = ET.fromstring(urdf_text)
    for element in root.iter("joint"):
        name = element.get("name")
        if name is None or element.find("parent") is None:
            continue  # transmission joints etc.
        origin = element.find("origin")
        if origin is None:
            origin = ET.SubElement(element, "origin")
        xyz, rpy = xyz_rpy_from_transform(tree.joint(name).origin)
        origin.set("xyz", " ".join(repr(float(v)) for v in xyz))
        origin.set("rpy", " ".join(repr(float(v)) for v in rpy))
    return resolve_meshes(ET.tostring(root, encoding="unicode"), urdf_dir, package_path)


def link_poses(pb, robot_id, link_index):
    """``{link: world2link (4, 4)}`` as pybullet holds them, for ``link_index`` ``{link name: pybullet index}``."""
    poses = {}
    for link, index in link_index.items():
        if index < 0:
            position, orientation = pb.getBasePositionAndOrientation(robot_id)
            # pybullet's base pose is its inertial frame; the URDF link frame is that times inertial^-1.
            inertial = pb.getDynamicsInfo(robot_id, -1)[3:5]
            position, orientation = pb.multiplyTransforms(position, orientation, *pb.invertTransform(*inertial))
        else:
            position, orientation = pb.getLinkState(robot_id, index, computeForwardKinematics=True)[4:6]
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_quat(orientation).as_matrix()
        pose[:3, 3] = position
        poses[link] = pose
    return poses
