"""ROS messages and bag writers from rosbags' own types, for the tests and the shipped sample bag.

:func:`joint_state` and :func:`pose_stamped` build the messages ``import-bag`` reads; :func:`bag_writer`
opens a ROS 1 bag or a ROS 2 bag directory with the matching type store and serialiser. Stamps are
``T0_S + t_s`` seconds since the epoch, as a robot's clock gives them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

T0_S = 1_700_000_000  # ROS stamps are seconds since the epoch
JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


def bag_writer(path: Path, kind: str) -> tuple[Writer1 | Writer2, object, Callable]:
    """``(writer, typestore, serialize)`` for ``kind`` = ros1 | ros2-sqlite3 | ros2-mcap; write a
    message with ``writer.write(connection, stamp_ns, serialize(msg, connection.msgtype))``."""
    ros1 = kind == "ros1"
    typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    serialize = typestore.serialize_ros1 if ros1 else typestore.serialize_cdr
    if ros1:
        return Writer1(path), typestore, serialize
    plugin = StoragePlugin.MCAP if kind == "ros2-mcap" else StoragePlugin.SQLITE3
    return Writer2(path, version=9, storage_plugin=plugin), typestore, serialize


def stamp_ns(t_s: float) -> int:
    """The bag's record time [ns] of a message stamped ``t_s`` [s after T0_S], in integers: a float
    of ~1.7e18 ns has steps of 256 ns."""
    return T0_S * 10**9 + round(t_s * 1e9)


def _time(typestore, t_s: float):
    sec = int(np.floor(t_s))
    return typestore.types["builtin_interfaces/msg/Time"](sec=T0_S + sec, nanosec=round((t_s - sec) * 1e9))


def _header(typestore, t_s: float):
    header = typestore.types["std_msgs/msg/Header"]
    ros1 = "seq" in header.__dataclass_fields__  # ROS 1 headers carry a sequence number
    return header(**({"seq": 0} if ros1 else {}), stamp=_time(typestore, t_s), frame_id="base")


def joint_state(typestore, t_s: float, names: list[str], positions) -> object:
    return typestore.types[JOINT_STATE](
        header=_header(typestore, t_s),
        name=names,
        position=np.asarray(positions, dtype=float),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def pose_stamped(typestore, t_s: float, pose) -> object:
    """``pose = [x, y, z m, roll, pitch, yaw rad]`` as a PoseStamped (``R = Rz Ry Rx``)."""
    types = typestore.types
    x, y, z, w = Rotation.from_euler("ZYX", pose[[5, 4, 3]]).as_quat()  # R = Rz Ry Rx; quat x, y, z, w
    return types[POSE_STAMPED](
        header=_header(typestore, t_s),
        pose=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=pose[0], y=pose[1], z=pose[2]),
            orientation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        ),
    )
