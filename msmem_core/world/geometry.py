"""Rigid-body helpers. Poses are 4x4 homogeneous matrices; quaternions are (x, y, z, w)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]
"""A float64 array: positions, rotations, poses, extents."""


def quat_to_matrix(q_xyzw: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix of a unit quaternion given as (x, y, z, w)."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: ArrayLike) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w) with w >= 0 of a 3x3 rotation matrix."""
    m = np.asarray(r, dtype=np.float64)[:3, :3]
    tr = np.trace(m)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    qa = np.asarray(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[3] < 0 else qa


def slerp(q0: NDArray[np.float64], q1: NDArray[np.float64], t: float) -> NDArray[np.float64]:
    """Spherical linear interpolation of unit quaternions (xyzw) along the shorter arc."""
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(d)
    return (math.sin((1 - t) * theta) * q0 + math.sin(t * theta) * q1) / math.sin(theta)


def quat_angle(q0: NDArray[np.float64], q1: NDArray[np.float64]) -> float:
    """Angle in radians between two unit quaternions."""
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))


def rotation_vector(r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Axis times angle of a rotation matrix."""
    q = matrix_to_quat(r)
    s = float(np.linalg.norm(q[:3]))
    if s < 1e-12:
        return np.zeros(3)
    return q[:3] / s * 2.0 * math.atan2(s, q[3])


def pose_matrix(position: ArrayLike, quat_xyzw: ArrayLike = (0, 0, 0, 1)) -> NDArray[np.float64]:
    """4x4 pose from a position and an (x, y, z, w) quaternion."""
    t = np.eye(4)
    t[:3, :3] = quat_to_matrix(quat_xyzw)
    t[:3, 3] = np.asarray(position, dtype=np.float64)
    return t


def yaw_quat(yaw_rad: float) -> NDArray[np.float64]:
    """Quaternion (x, y, z, w) of a rotation about world z."""
    return np.array([0.0, 0.0, np.sin(yaw_rad / 2), np.cos(yaw_rad / 2)])


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0, 0, 1)) -> NDArray[np.float64]:
    """Camera-to-world pose in the OpenCV convention (x right, y down, z forward) looking at target."""
    eye_a = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye_a
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any perpendicular
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = x, y, z, eye_a
    return t


def rotation_angle_deg(r_a: ArrayLike, r_b: ArrayLike) -> float:
    """Angle in degrees of the relative rotation between two rotation matrices."""
    r = np.asarray(r_a)[:3, :3].T @ np.asarray(r_b)[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def boxes_overlap(ca: F64, ra: F64, ha: F64, cb: F64, rb: F64, hb: F64, margin: float = 0.0) -> NDArray[np.bool_]:
    """Separating-axis test of M oriented boxes A against one oriented box B: True where they overlap.

    A box is its centre, its rotation (columns: the box's axes in the world) and its half extents: A as
    ``ca [M, 3]``, ``ra [M, 3, 3]``, ``ha [M, 3]``, B as ``cb [3]``, ``rb [3, 3]``, ``hb [3]``. Boxes that
    touch overlap. ``margin`` (metres) is a tolerance: boxes whose gap is at most ``margin`` count as
    overlapping too (at least ``margin``: on an edge-edge axis the projections are not normalised).
    The candidate axes are the 3 + 3 face normals and the 9 cross products of the boxes' edges; the
    1e-12 added to the rotation terms keeps near-parallel edges (whose cross product vanishes) from
    separating boxes that overlap.
    """
    r = np.einsum("mji,jk->mik", ra, rb)  # B's axes in A's frame: r[m, i, k] = a_i . b_k
    t = np.einsum("mji,mj->mi", ra, cb - ca)  # centre offset in A's frame
    ar = np.abs(r) + 1e-12
    sep = np.zeros(len(ca), dtype=bool)
    for i in range(3):  # A's face axes
        sep |= np.abs(t[:, i]) > ha[:, i] + ar[:, i, :] @ hb + margin
    for k in range(3):  # B's face axes
        sep |= np.abs(np.einsum("mi,mi->m", t, r[:, :, k])) > np.einsum("mi,mi->m", ha, ar[:, :, k]) + hb[k] + margin
    for i in range(3):  # cross products a_i x b_k
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for k in range(3):
            k1, k2 = (k + 1) % 3, (k + 2) % 3
            dist = np.abs(t[:, i2] * r[:, i1, k] - t[:, i1] * r[:, i2, k])
            ra_ = ha[:, i1] * ar[:, i2, k] + ha[:, i2] * ar[:, i1, k]
            rb_ = hb[k1] * ar[:, i, k2] + hb[k2] * ar[:, i, k1]
            sep |= dist > ra_ + rb_ + margin
    return ~sep
