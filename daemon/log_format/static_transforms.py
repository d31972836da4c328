"""The car's static transforms as Foxglove sees them: one `foxglove.FrameTransforms` message from the vehicle frame to
every sensor's frame (each camera's optical frame by its name, the Lidar, the GNSS antenna, the IMU), from the
config's extrinsics, so the 3D panel places each sensor's data on the car. Each transform is stamped at time 0: Foxglove
looks a frame's transforms up at a message's payload stamp (a host-monotonic time here, a sensor's clock elsewhere)
and takes one stamped at or before it, so a static transform stamped 0 holds at every time, whatever the clock."""

from __future__ import annotations

import math

from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

from daemon.spine.config import CarConfig, Extrinsics
from daemon.spine.topics import VEHICLE_FRAME

LIDAR_FRAME = "lidar"  # the frame_id of the Lidar's point clouds (PointCloud.sensor's default)
GNSS_FRAME = "gnss"  # the frame_id of the GNSS fixes (foxglove_schemas)
IMU_FRAME = "imu"


def rpy_quaternion(roll_deg: float, pitch_deg: float, yaw_deg: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) @ Ry(pitch) @ Rx(roll), the config's convention."""
    r, p, y = (math.radians(a) / 2 for a in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def sensor_frames(config: CarConfig) -> dict[str, Extrinsics]:
    """Every sensor frame of the car with its pose in the vehicle frame."""
    s = config.sensors
    frames = {cam.name: cam.extrinsics for cam in s.cameras}
    if s.lidar is not None:
        frames[LIDAR_FRAME] = s.lidar.extrinsics
    if s.gnss is not None:
        frames[GNSS_FRAME] = Extrinsics(translation_m=s.gnss.antenna_lever_arm_m)
        frames[IMU_FRAME] = s.gnss.imu_extrinsics
    return frames


def static_transforms(config: CarConfig) -> FrameTransforms:
    """vehicle -> each sensor frame: the child's pose in the parent (translation, rotation), as ROS tf and Foxglove
    take a transform, stamped 0 (valid at every time)."""
    out = FrameTransforms()
    for name, extrinsics in sensor_frames(config).items():
        tf = out.transforms.add(parent_frame_id=VEHICLE_FRAME, child_frame_id=name)
        tf.timestamp.SetInParent()  # written, as 0 (a reader that requires the field finds it)
        tf.translation.x, tf.translation.y, tf.translation.z = extrinsics.translation_m
        q = tf.rotation
        q.x, q.y, q.z, q.w = rpy_quaternion(*extrinsics.rotation_rpy_deg)
    return out
