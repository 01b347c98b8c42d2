"""DAIR-V2X's box convention, carried into the contract's camera frame.

A DAIR-V2X box lives in the virtual-LiDAR frame (x forward, y left, z up): `3d_location` is the
box centre, `3d_dimensions` give l w h with l along the heading, and `rotation` is the yaw about +z,
0 along +x. The object frame's axes are the LiDAR's turned by that yaw, so the object-to-LiDAR
rotation is rot_z(yaw), and X_cam = R X_lidar + t (`virtuallidar_to_camera`) carries the camera's
pitch into the box's rotation. The official DAIR-to-KITTI converter is not used: it writes the
heading 90 degrees off and drops the pitch. Reading DAIR-V2X trees (files, calibration, labels,
ground plane) is converters/dair.py's; every choice: docs/converters-dair.md.
"""

from __future__ import annotations

import numpy as np

from omnigen.geometry import Box3D, rots_z


def box_from_dair(center_lidar: np.ndarray, lwh: np.ndarray, yaw: float,
                  lidar_to_camera_rotation: np.ndarray, lidar_to_camera_translation: np.ndarray,
                  center_transform: np.ndarray | None = None) -> Box3D:
    """A DAIR-V2X box (virtual-LiDAR centre, [l, w, h], yaw about +z, 0 along +x) in the camera.

    The object frame's axes coincide with the virtual LiDAR's (x forward, y left, z up) rotated by
    the yaw, so the object-to-LiDAR rotation is rot_z(yaw); X_cam = R X_lidar + t then carries
    the camera's pitch into the box's rotation. `center_transform` (default R) maps the centre:
    the calibrated matrix, where R is its nearest proper rotation. boxes_from_dair on a batch of one.
    """
    centers, rotations = boxes_from_dair(center_lidar, [yaw], lidar_to_camera_rotation,
                                         lidar_to_camera_translation, center_transform)
    return Box3D(centers[0], lwh, rotations[0])


def boxes_from_dair(centers_lidar: np.ndarray, yaws: np.ndarray, lidar_to_camera_rotation: np.ndarray,
                    lidar_to_camera_translation: np.ndarray,
                    center_transform: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(centers (N, 3), rotations (N, 3, 3)) in the camera of N DAIR-V2X boxes; dims are unchanged.

    box_from_dair is this on a batch of one, so a box is the same alone or in a batch: rots_z is
    rot_z entry for entry (cosine and sine from math) and every box goes through the same 3x3 products.
    """
    centers_lidar = np.asarray(centers_lidar, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(lidar_to_camera_rotation, dtype=np.float64)
    m = r if center_transform is None else np.asarray(center_transform, dtype=np.float64)
    t = np.asarray(lidar_to_camera_translation, dtype=np.float64).reshape(3)
    centers = (m @ centers_lidar[:, :, None])[:, :, 0] + t
    return centers, r @ rots_z(yaws)
