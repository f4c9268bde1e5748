"""``ur5e``: a Universal Robots UR5e with a Robotiq 2F-85 gripper and a wrist camera, the paper's robot but
for the e-series arm (the UR5's successor, the same reach of 850 mm). Its description comes from the
``airo-models`` package on PyPI (MIT licence; the URDFs and meshes of ``ur5e`` and ``robotiq_2f_85``):
the two are joined at the arm's ``tool0`` into one URDF, written once into ``$MSMEM_CACHE_DIR/robots``
(the packaged files carry Drake extensions that other URDF readers refuse; they are left out, and mesh
paths made absolute). IK, collisions and paths are ``msmem_robots.arm.PybulletArm``'s; docs/explanation/robots.md,
"The UR5e".
"""

from __future__ import annotations

import hashlib
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np

from msmem_core.errors import PluginError
from msmem_core.interfaces import RobotModel
from msmem_core.util.artifacts import cache_root, tmp_path
from msmem_robots.arm import PybulletArm
from msmem_robots.config import UR5eConfig

ARM_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
              "wrist_3_joint")
GRIPPER_JOINTS = ("finger_joint", "left_inner_finger_joint", "left_inner_knuckle_joint", "right_outer_knuckle_joint",
                  "right_inner_finger_joint", "right_inner_knuckle_joint")
"""The 2F-85's movable joints in the joined URDF's order: the driver ``finger_joint`` (0 open, 0.8 closed) and
the linkage joints that follow it (``GRIPPER_GEARING``)."""
GRIPPER_GEARING = (1.0, -1.0, 1.0, 1.0, -1.0, 1.0)
"""Each gripper joint's position per radian of ``finger_joint`` (the URDF's mimic multipliers)."""
HAND_LINKS = ("wrist_3_link", "flange", "tool0", "gripper_base_link", "gripper_base_link_inertia",
              "left_outer_knuckle", "left_outer_finger", "left_inner_finger", "left_inner_finger_pad",
              "left_inner_knuckle", "right_outer_knuckle", "right_outer_finger", "right_inner_finger",
              "right_inner_finger_pad", "right_inner_knuckle")
"""The links that move rigidly with the wrist camera, the gripper's linkage included (its parts touch: their
pairs are not checked against each other)."""
FINGER_PADS = ("left_inner_finger_pad", "right_inner_finger_pad")
FINGER_CLOSED_RAD = 0.8
"""``finger_joint`` fully closed (the URDF's upper limit; 0 is open)."""
OPENING_SAMPLES = 17
FINGERTIP_M = 0.15
"""From ``tool0`` along its z to the tips of the open 2F-85's pads (0.149 m; 0.163 m closed)."""
BUILD_VERSION = 1
# chosen greedily by examples/robots/ur5e_starts.py (docs/explanation/robots.md)
STARTS: tuple[tuple[float, ...], ...] = (
    (-0.775, -1.724, 0.445, -0.498, -2.821, -0.336),
    (0.256, -1.041, 1.55, 0.264, -0.17, -1.591),
    (0.329, -1.96, 0.394, -3.08, -0.18, 1.321),
)
"""Start configurations (and null-space rest poses) of the IK, tried in this order; ``ik_starts`` of them.
The first is also where a simulator parks the arm."""


def _clean(text: str) -> str:
    """The URDF without Drake's extensions (namespaced tags and attributes the file does not declare)."""
    text = re.sub(r"<drake:[\s\S]*?</drake:[\w:]+>", "", text)
    text = re.sub(r"<drake:[^>]*/>", "", text)
    return re.sub(r'\s+drake:\w+="[^"]*"', "", text)


def _sources() -> tuple[Path, Path]:
    try:
        from airo_models.files import get_urdf_path
    except ImportError as e:
        raise PluginError("robot ur5e needs the airo-models package (its UR5e and Robotiq 2F-85 URDFs): "
                          "pip install airo-models") from e
    return Path(get_urdf_path("ur5e")), Path(get_urdf_path("robotiq_2f_85"))


def joined_urdf() -> Path:
    """The UR5e with the 2F-85 fixed at its ``tool0`` (built on first use, then read from the cache)."""
    arm_path, hand_path = _sources()
    digest = hashlib.sha256()
    for part in (str(BUILD_VERSION), str(arm_path), arm_path.read_text(), str(hand_path), hand_path.read_text()):
        digest.update(part.encode())
    out = cache_root("robots") / f"ur5e-2f85-{digest.hexdigest()[:16]}.urdf"
    if out.is_file():
        return out

    def load(path: Path) -> ET.Element:
        root = ET.fromstring(_clean(path.read_text()))
        for mesh in root.iter("mesh"):
            mesh.set("filename", os.path.normpath(path.parent / mesh.get("filename", "")))
        return root

    arm, hand = load(arm_path), load(hand_path)
    renamed = {"base_link": "gripper_base_link", "base_link_inertia": "gripper_base_link_inertia"}
    for el in hand.iter():
        if el.tag == "link" and el.get("name") in renamed:
            el.set("name", renamed[el.get("name", "")])
        if el.tag in ("parent", "child") and el.get("link") in renamed:
            el.set("link", renamed[el.get("link", "")])
    for el in list(hand):
        if el.tag in ("link", "joint"):
            arm.append(el)
    joint = ET.SubElement(arm, "joint", name="tool0-gripper", type="fixed")
    ET.SubElement(joint, "parent", link="tool0")
    ET.SubElement(joint, "child", link="gripper_base_link")
    ET.SubElement(joint, "origin", xyz="0 0 0", rpy="0 0 0")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = tmp_path(out)
    ET.ElementTree(arm).write(tmp)
    os.replace(tmp, out)
    return out


class UR5eRobot(PybulletArm):
    """UR5e with a Robotiq 2F-85 and a wrist camera; base in front of the shelf (``UR5eConfig``)."""

    name = "ur5e"
    arm_joints = len(ARM_JOINTS)
    flange_link = "tool0"
    finger_joints = GRIPPER_JOINTS
    finger_open = (0.0,) * len(GRIPPER_JOINTS)
    fingertip_m = FINGERTIP_M
    camera_carriers = HAND_LINKS
    hand_links = HAND_LINKS
    last_link = "gripper_base_link"
    starts = STARTS

    def __init__(self, config: UR5eConfig | None = None) -> None:
        super().__init__(config or UR5eConfig())
        self._table: tuple[tuple[float, float], ...] | None = None

    def urdf(self) -> Path:
        return joined_urdf()

    def model(self) -> RobotModel:
        """The arm's model, with the 2F-85 as a linkage: its joints geared to ``finger_joint`` and the
        opening between the pads measured in the robot's client at ``OPENING_SAMPLES`` positions of it."""
        m = super().model()
        return replace(m, finger_gearing=GRIPPER_GEARING, finger_opening=self._opening_table(),
                       finger_pads=FINGER_PADS)

    def _opening_table(self) -> tuple[tuple[float, float], ...]:
        if self._table is None:
            c = self._connect()
            pads = [next(j for j, n in self._links.items() if n == pad) for pad in FINGER_PADS]
            drive = self._movable[self.arm_joints:]
            out = []
            for theta in np.linspace(0.0, FINGER_CLOSED_RAD, OPENING_SAMPLES):
                for j, g in zip(drive, GRIPPER_GEARING, strict=True):
                    c.resetJointState(self._body, j, float(g * theta))
                gap = c.getClosestPoints(self._body, self._body, 0.2, pads[0], pads[1])
                out.append((float(theta), float(min(p[8] for p in gap))))
            self._set(np.asarray(self.starts[0]))
            self._table = tuple(out)
        return self._table
