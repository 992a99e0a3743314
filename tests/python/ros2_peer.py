"""A ROS 2 peer built on an independent DDS implementation (Eclipse Cyclone DDS's Python
binding): it plays the /odom and /points messages of a rosbag2 MCAP recording onto the ROS 2
topics `rt/odom` and `rt/points` (ROS 2's DDS names and types, classic CDR), and receives the
bridge's grid_map_msgs/GridMap and nav_msgs/OccupancyGrid.

Protocol on stdout / stdin, one line each:
  -> "matched"            the bridge's reader and writers were discovered
  -> "published N"        N clouds written (each after its odometry)
  <- "go T"               the test's clock (ns) after which the map no longer changes
  -> "wrote"              OUT holds the first GridMap and OccupancyGrid stamped at or after T

Usage: ros2_peer.py IN.mcap OUT.json DOMAIN_ID [PERIOD_S]
"""

import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float32, float64, int8, int32, sequence, uint8, uint16, uint32
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from mcap.reader import make_reader

WAIT_S = 30.0


def ros(pkg: str, name: str) -> str:
    return f"{pkg}::msg::dds_::{name}_"


@dataclass
class Time(IdlStruct, typename=ros("builtin_interfaces", "Time")):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename=ros("std_msgs", "Header")):
    stamp: Time
    frame_id: str


@dataclass
class PointField(IdlStruct, typename=ros("sensor_msgs", "PointField")):
    name: str
    offset: uint32
    datatype: uint8
    count: uint32


@dataclass
class PointCloud2(IdlStruct, typename=ros("sensor_msgs", "PointCloud2")):
    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool


@dataclass
class Point(IdlStruct, typename=ros("geometry_msgs", "Point")):
    x: float64
    y: float64
    z: float64


@dataclass
class Vector3(IdlStruct, typename=ros("geometry_msgs", "Vector3")):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename=ros("geometry_msgs", "Quaternion")):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename=ros("geometry_msgs", "Pose")):
    position: Point
    orientation: Quaternion


@dataclass
class PoseWithCovariance(IdlStruct, typename=ros("geometry_msgs", "PoseWithCovariance")):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class Twist(IdlStruct, typename=ros("geometry_msgs", "Twist")):
    linear: Vector3
    angular: Vector3


@dataclass
class TwistWithCovariance(IdlStruct, typename=ros("geometry_msgs", "TwistWithCovariance")):
    twist: Twist
    covariance: array[float64, 36]


@dataclass
class Odometry(IdlStruct, typename=ros("nav_msgs", "Odometry")):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance


@dataclass
class MultiArrayDimension(IdlStruct, typename=ros("std_msgs", "MultiArrayDimension")):
    label: str
    size: uint32
    stride: uint32


@dataclass
class MultiArrayLayout(IdlStruct, typename=ros("std_msgs", "MultiArrayLayout")):
    dim: sequence[MultiArrayDimension]
    data_offset: uint32


@dataclass
class Float32MultiArray(IdlStruct, typename=ros("std_msgs", "Float32MultiArray")):
    layout: MultiArrayLayout
    data: sequence[float32]


@dataclass
class GridMapInfo(IdlStruct, typename=ros("grid_map_msgs", "GridMapInfo")):
    resolution: float64
    length_x: float64
    length_y: float64
    pose: Pose


@dataclass
class GridMap(IdlStruct, typename=ros("grid_map_msgs", "GridMap")):
    header: Header
    info: GridMapInfo
    layers: sequence[str]
    basic_layers: sequence[str]
    data: sequence[Float32MultiArray]
    outer_start_index: uint16
    inner_start_index: uint16


@dataclass
class MapMetaData(IdlStruct, typename=ros("nav_msgs", "MapMetaData")):
    map_load_time: Time
    resolution: float32
    width: uint32
    height: uint32
    origin: Pose


@dataclass
class OccupancyGrid(IdlStruct, typename=ros("nav_msgs", "OccupancyGrid")):
    header: Header
    info: MapMetaData
    data: sequence[int8]


def stamp_ns(header: Header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def pose_json(p: Pose) -> dict:
    return {"x": p.position.x, "y": p.position.y, "z": p.position.z, "qw": p.orientation.w}


def until(what: str, done) -> None:
    """Polls `done` every 10 ms for at most WAIT_S seconds."""
    deadline = time.monotonic() + WAIT_S
    while not done():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.01)


def say(line: str) -> None:
    print(line, flush=True)


def main(src: str, out: str, domain: int, period_s: float) -> None:
    # Classic CDR (XCDR1), as rmw_cyclonedds and rmw_fastrtps send ROS 2 messages.
    cdr = Policy.DataRepresentation(use_cdrv0_representation=True)
    reliable = Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1))
    sensor = Qos(reliable, Policy.History.KeepLast(8), cdr)
    latched = Qos(reliable, Policy.Durability.TransientLocal, Policy.History.KeepLast(1), cdr)
    dp = DomainParticipant(domain)
    points = DataWriter(dp, Topic(dp, "rt/points", PointCloud2), qos=sensor)
    odom = DataWriter(dp, Topic(dp, "rt/odom", Odometry), qos=sensor)
    grids = DataReader(dp, Topic(dp, "rt/rangegp/grid_map", GridMap), qos=latched)
    costs = DataReader(dp, Topic(dp, "rt/rangegp/costmap", OccupancyGrid), qos=latched)
    until("the bridge's cloud reader", lambda: len(points.get_matched_subscriptions()) > 0)
    until("the bridge's odometry reader", lambda: len(odom.get_matched_subscriptions()) > 0)
    until("the bridge's grid writer", lambda: len(grids.get_matched_publications()) > 0)
    until("the bridge's costmap writer", lambda: len(costs.get_matched_publications()) > 0)
    say("matched")

    clouds = 0
    with open(src, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/odom", "/points"]):
            if channel.topic == "/odom":
                odom.write(Odometry.deserialize(message.data))
            else:
                points.write(PointCloud2.deserialize(message.data))
                clouds += 1
                # The sensor's rate: one cloud each period, as a driver sends them.
                time.sleep(period_s)
    say(f"published {clouds}")

    line = sys.stdin.readline().split()
    if len(line) != 2 or line[0] != "go":
        raise SystemExit(f"expected 'go T', got {line}")
    after = int(line[1])
    latest = {"grid": None, "cost": None}

    def fresh() -> bool:
        for key, reader in (("grid", grids), ("cost", costs)):
            for m in reader.take(N=16):
                if stamp_ns(m.header) >= after:
                    latest[key] = m
        return latest["grid"] is not None and latest["cost"] is not None

    until("a grid made after the map settled", fresh)
    g, c = latest["grid"], latest["cost"]
    result = {
        "grid_map": {
            "frame_id": g.header.frame_id,
            "stamp_ns": stamp_ns(g.header),
            "resolution": g.info.resolution,
            "length_x": g.info.length_x,
            "length_y": g.info.length_y,
            "pose": pose_json(g.info.pose),
            "layers": list(g.layers),
            "basic_layers": list(g.basic_layers),
            "data": [
                {
                    "dims": [[d.label, d.size, d.stride] for d in a.layout.dim],
                    "values": [None if v != v else v for v in a.data],
                }
                for a in g.data
            ],
            "outer_start_index": g.outer_start_index,
            "inner_start_index": g.inner_start_index,
        },
        "occupancy": {
            "frame_id": c.header.frame_id,
            "stamp_ns": stamp_ns(c.header),
            "resolution": c.info.resolution,
            "width": c.info.width,
            "height": c.info.height,
            "origin": pose_json(c.info.origin),
            "data": list(c.data),
        },
    }
    with open(out, "w") as f:
        json.dump(result, f)
    say("wrote")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4]) if len(sys.argv) > 4 else 0.2)
