"""Config models of the built-in robots (importable without pybullet)."""

from __future__ import annotations

from pydantic import BaseModel, Field, PositiveFloat

from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Bool, Int

Vec3 = tuple[float, float, float]
Sizes3 = tuple[PositiveFloat, PositiveFloat, PositiveFloat]


class FloatingConfig(BaseModel):
    """The floating gripper and camera: no arm, no parameters."""

    model_config = FROZEN_MODEL_CONFIG


class ArmConfig(BaseModel):
    """An arm in pybullet with a wrist camera (``msmem_robots.arm.PybulletArm``); the defaults are the Panda's."""

    model_config = FROZEN_MODEL_CONFIG

    base_position_m: Vec3 = (0.0, -0.55, -0.3)
    """Base position in the shelf frame (x along the shelf, y into it from its open front at y = 0, z up
    from its floor): centred, 55 cm in front of the shelf, 30 cm below its floor (docs/explanation/robots.md has the
    sweep this was chosen from)."""
    base_yaw_deg: float = Field(90.0, ge=-180.0, le=180.0)
    """Rotation of the base about z; 90 faces the shelf (+y)."""
    camera_offset_m: Vec3 = (-0.042, 0.042, 0.03)
    """Wrist camera position (its optical centre) in the flange frame (``panda_link8``: z along the last
    joint's axis, out of the flange): 6 cm from the flange axis across the hand's thickness (the hand
    is turned -45 deg about z), 3 cm out, so that its body (``camera_box_m``) clears the hand."""
    camera_rpy_deg: Vec3 = (10.0, 0.0, 45.0)
    """Wrist camera orientation in the flange frame (roll, pitch, yaw about the flange's x, y, z, applied
    in that order): the camera (OpenCV: x right, y down, z forward) looks along the flange's z tilted 10
    deg towards the fingers, so that their tips are in the top of the picture, its x along the hand's
    width."""
    camera_box_m: Sizes3 | None = (0.09, 0.025, 0.025)
    """The camera's body, a box of these sizes along the camera's x, y and z (a RealSense D435 is
    90 x 25 x 25 mm), its front face centred on the optical centre. It is checked for collisions like
    the arm's links (``camera-<board>``, ``camera-<link>`` for the links from ``panda_link0`` to
    ``panda_link5``), and a mount that puts it into the hand, the fingers or ``panda_link7`` is refused
    when the robot is built. None: no camera body."""
    collision_margin_m: float = Field(0.01, ge=0.0, le=0.2)
    """An arm link closer than this to a shelf board collides."""
    self_collision: bool = True
    """Also refuse configurations in which two of the arm's links touch (pairs at least three joints
    apart along the chain: neighbours and the two fingers always touch or nearly)."""
    position_tolerance_m: float = Field(0.005, gt=0.0, le=0.1)
    """Largest flange position error (forward kinematics of the IK answer) counted as reached."""
    orientation_tolerance_deg: float = Field(2.0, gt=0.0, le=45.0)
    """Largest flange orientation error counted as reached."""
    ik_iterations: Int = Field(100, ge=1, le=10000)
    """pybullet IK iterations per call."""
    ik_rounds: Int = Field(4, ge=1, le=100)
    """IK calls per start configuration, each from the previous answer (clipped to the joint limits)."""
    ik_starts: Int = Field(8, ge=1, le=8)
    """Start configurations tried in turn (the first ones of a fixed list; docs/explanation/robots.md)."""
    path_joint_step_rad: float = Field(0.5, gt=0.0, le=6.3)
    """Along a tool path (``reach_path``), the largest change of any joint between consecutive path points
    (at most 2 cm apart); a larger one means the arm would have to jump to another configuration."""
    disk_cache: Bool = True
    """Keep reachable-view answers in ``$MSMEM_CACHE_DIR/reach`` (default ``~/.cache/msmem/reach``)."""


class PandaConfig(ArmConfig):
    """The Franka Panda of ``pybullet_data`` (``franka_panda/panda.urdf``) with a wrist camera."""


class UR5eConfig(ArmConfig):
    """A UR5e with a Robotiq 2F-85 (``airo-models``' URDFs, MIT) and a wrist camera (docs/explanation/robots.md,
    "The UR5e")."""

    base_position_m: Vec3 = (0.0, -0.65, -0.3)
    """Base position in the shelf frame: centred, 65 cm in front of the shelf, 30 cm below its floor (the
    sweep in docs/explanation/robots.md)."""
    camera_offset_m: Vec3 = (0.0, 0.06, 0.03)
    """Wrist camera position in the flange frame (``tool0``: z out of the flange, the 2F-85's fingers close
    along x): 6 cm across the gripper's thickness, on the side that is up when the hand points into the
    shelf with its back up, 3 cm out."""
    camera_rpy_deg: Vec3 = (10.0, 0.0, 0.0)
    """Wrist camera orientation in the flange frame: looking along its z, tilted 10 deg towards the fingers,
    its x along the fingers' closing axis."""
