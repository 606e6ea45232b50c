"""The state of N rigid objects: the initial state a motion starts from, the trajectory it makes, pose helpers.

Shared by the motion models (flowsynth.scene.motion: kinematic, static; flowsynth.scene.physics: Newton). Plain numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["InitialState", "Trajectory", "pose_matrices", "quat_to_rotation", "rotation_to_quat_xyzw",
           "simulate_static"]


@dataclass(frozen=True)
class InitialState:
    """State of N objects at t = 0, world frame.

    Attributes:
        position: (N, 3) float64 object origins [m].
        rotation: (N, 3, 3) float64 world_R_obj.
        velocity: (N, 3) float64 linear velocities [m/s].
        angular_velocity: (N, 3) float64 angular velocities [rad/s], world axes.
    """

    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray


@dataclass(frozen=True)
class Trajectory:
    """Motion of N objects over T frames.

    Attributes:
        poses: (T, N, 4, 4) float64 world_T_obj at t_k = k / fps.
        velocity: (T, N, 3) float64 linear velocities at t_k [m/s].
        angular_velocity: (T, N, 3) float64 angular velocities at t_k [rad/s], world axes.
        substeps: physics substeps per frame (0 for kinematic and static).
    """

    poses: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    substeps: int


def simulate_static(initial: InitialState, num_frames: int) -> Trajectory:
    """Every pose equals the initial pose; velocities are zero."""
    poses = np.tile(pose_matrices(initial.position, initial.rotation)[None], (num_frames, 1, 1, 1))
    zeros = np.zeros((num_frames, len(initial.position), 3))
    return Trajectory(poses, zeros, zeros.copy(), 0)



def pose_matrices(position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(..., 4, 4) world_T_obj of positions (..., 3) [m] and rotations (..., 3, 3)."""
    P = np.zeros(position.shape[:-1] + (4, 4))
    P[..., :3, :3] = rotation
    P[..., :3, 3] = position
    P[..., 3, 3] = 1.0
    return P


def quat_to_rotation(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w), renormalised, to (N, 3, 3) float64 rotation matrices."""
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def rotation_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices to (N, 4) unit quaternions (x, y, z, w), w >= 0."""
    q = Rotation.from_matrix(R).as_quat()  # scipy order is (x, y, z, w)
    return q * np.where(q[:, 3:] < 0, -1.0, 1.0)
