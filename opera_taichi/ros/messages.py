"""ROS messages of the topic table, built and (de)serialised with rosbags' type stores.

One serialiser for every way out: ROS 1 wire format for the rospy node, the ROS 1 endpoint and `.bag` files; CDR for
the ROS 2 endpoint and `.mcap` files. ROS 1 types come from rosbags' Noetic store, ROS 2 types from its Humble store;
both get OPERA's com3_msgs/JointCmd (and ROS 1 gets tf2_msgs/TFMessage, which Noetic's store lacks) from their
.msg text, so their definitions and ROS 1 md5 sums are those of the real packages (tests compare them with genpy's).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

# com3_msgs/msg/JointCmd.msg of OPERA's com3_ros (pwri-opera, Apache-2.0), fields only; tests check it against
# ../shared/thirdparty/com3_msgs/msg/JointCmd.msg and genpy's md5 sum. control_type: 0 position, 1 velocity, 2 effort.
JOINT_CMD_MSG = """string[] joint_name
uint8 control_type
float64[] position
float64[] velocity
float64[] effort
"""
TF_MESSAGE_MSG = "geometry_msgs/TransformStamped[] transforms\n"
WORLD_FRAME = "world"


@lru_cache(maxsize=None)
def typestore(ros_version: int):
    """rosbags' type store for ROS 1 (Noetic) or ROS 2 (Humble) with the extra types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    extra = get_types_from_msg(JOINT_CMD_MSG, "com3_msgs/msg/JointCmd")
    if "tf2_msgs/msg/TFMessage" not in store.types:
        extra.update(get_types_from_msg(TF_MESSAGE_MSG, "tf2_msgs/msg/TFMessage"))
    store.register(extra)
    return store


def serialize(store, ros_version: int, msg, typename: str) -> bytes:
    if ros_version == 1:
        return bytes(store.serialize_ros1(msg, typename))
    return bytes(store.serialize_cdr(msg, typename, little_endian=True))


def deserialize(store, ros_version: int, data: bytes, typename: str):
    if ros_version == 1:
        return store.deserialize_ros1(data, typename)
    return store.deserialize_cdr(data, typename)


def msgdef(store, typename: str, ros_version: int) -> tuple[str, str]:
    """(definition text with its dependencies, ROS 1 md5 sum) as ROS tools and bag formats want them."""
    return store.generate_msgdef(typename, ros_version=ros_version)


def stamp(t: float) -> tuple[int, int]:
    ns = int(round(t * 1e9))
    return divmod(ns, 1_000_000_000)


class MessageBuilder:
    """Turns the sampler's plain data into messages of one type store (stateful only for ROS 1 header seq)."""

    def __init__(self, ros_version: int):
        self.ros_version = ros_version
        self.store = typestore(ros_version)
        self.T = self.store.types
        self._seq: dict[str, int] = {}

    def get_state(self) -> dict:
        """The ROS 1 header seq of each topic, so that a resumed run's messages go on counting."""
        return dict(self._seq)

    def set_state(self, state: dict) -> None:
        self._seq.update({str(k): int(v) for k, v in state.items()})

    def serialize(self, msg, typename: str) -> bytes:
        return serialize(self.store, self.ros_version, msg, typename)

    def time(self, t: float):
        sec, nsec = stamp(t)
        return self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)

    def header(self, topic: str, t: float, frame: str):
        H = self.T["std_msgs/msg/Header"]
        if self.ros_version == 1:
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            return H(seq=seq, stamp=self.time(t), frame_id=frame)
        return H(stamp=self.time(t), frame_id=frame)

    def _vec(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _pose(self, pos, quat):
        T = self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(pos[0]), y=float(pos[1]), z=float(pos[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=float(quat[0]), y=float(quat[1]), z=float(quat[2]),
                                                          w=float(quat[3])))

    def build(self, topic, data):
        """The message of `topic` (a topics.Topic) from the sampler's data for it."""
        T, name, t = self.T, topic.name, data["t"]
        kind = topic.type
        if kind == "rosgraph_msgs/msg/Clock":
            return T[kind](clock=self.time(t))
        if kind == "sensor_msgs/msg/JointState":
            return T[kind](header=self.header(name, t, ""), name=list(data["names"]),
                           position=np.asarray(data["q"], np.float64), velocity=np.asarray(data["qd"], np.float64),
                           effort=np.asarray(data["effort"], np.float64))
        if kind == "std_msgs/msg/Float64":
            return T[kind](data=float(data["value"]))
        if kind == "geometry_msgs/msg/PoseStamped":
            return T[kind](header=self.header(name, t, WORLD_FRAME), pose=self._pose(data["pos"], data["quat"]))
        if kind == "nav_msgs/msg/Odometry":
            zero = np.zeros(36, np.float64)
            return T[kind](header=self.header(name, t, WORLD_FRAME), child_frame_id=data["frame"],
                           pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(data["pos"], data["quat"]),
                                                                          covariance=zero),
                           twist=T["geometry_msgs/msg/TwistWithCovariance"](
                               twist=T["geometry_msgs/msg/Twist"](linear=self._vec(data["v_local"]),
                                                                  angular=self._vec(data["w_local"])),
                               covariance=zero.copy()))
        if kind == "geometry_msgs/msg/WrenchStamped":
            return T[kind](header=self.header(name, t, data["frame"]),
                           wrench=T["geometry_msgs/msg/Wrench"](force=self._vec(data["force"]),
                                                                torque=self._vec(data["torque"])))
        if kind == "tf2_msgs/msg/TFMessage":
            Q, TS = T["geometry_msgs/msg/Quaternion"], T["geometry_msgs/msg/TransformStamped"]
            transforms = [TS(header=self.header(f"{name}#{child}", t, parent), child_frame_id=child,
                             transform=T["geometry_msgs/msg/Transform"](
                                 translation=self._vec(pos),
                                 rotation=Q(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))
                          for parent, child, pos, q in data["transforms"]]
            return T[kind](transforms=transforms)
        if kind == "sensor_msgs/msg/PointCloud2":
            return self.point_cloud(name, t, data["x"], data["y"], data["z"])
        raise ValueError(f"no builder for {kind}")

    def point_cloud(self, topic: str, t: float, x: np.ndarray, y: np.ndarray, z: np.ndarray):
        """The heightmap z[ix, iy] as an organised cloud (height = len(y) rows of width len(x)), float32 x, y, z."""
        T = self.T
        F = T["sensor_msgs/msg/PointField"]
        ny, nx = len(y), len(x)
        xx, yy = np.meshgrid(np.asarray(x, np.float32), np.asarray(y, np.float32))   # (ny, nx)
        pts = np.stack([xx, yy, np.asarray(z, np.float32).T], axis=-1)                 # (ny, nx, 3)
        fields = [F(name=n, offset=4 * i, datatype=F.FLOAT32, count=1) for i, n in enumerate("xyz")]
        return T["sensor_msgs/msg/PointCloud2"](
            header=self.header(topic, t, WORLD_FRAME), height=ny, width=nx, fields=fields, is_bigendian=False,
            point_step=12, row_step=12 * nx, data=np.frombuffer(pts.astype("<f4").tobytes(), np.uint8),
            is_dense=bool(np.all(np.isfinite(pts))))


def finite(*values) -> bool:
    return all(math.isfinite(float(v)) for v in values)
