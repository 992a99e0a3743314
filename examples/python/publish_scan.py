#!/usr/bin/env python3
"""Publish one LiDAR scan to a rangegp daemon through iceoryx2 shared memory.

Needs only `pip install iceoryx2==0.10.0`. The ctypes structures below mirror
rangegp-proto's `ScanHeader` and `ScanPoint` byte for byte (docs/PROTOCOL.md).

The scan is the seed-000 scanner (16 rings, -15..0 deg; 91 columns, -90..90 deg; 10 m)
looking at flat ground at z = 0 from `--x --y` at 0.75 m, heading `--heading` (radians):
ranges are exact, so the daemon's elevation there should come back as 0.

    python3 publish_scan.py --service rangegp/default/scans --x 0 --y 0
"""
import argparse
import ctypes
import math
import sys
import time

import iceoryx2 as iox2

PROTOCOL_VERSION = 8
FLAG_NO_RETURN = 1
FLAG_RING_COLUMN_VALID = 2


class ScanHeader(ctypes.Structure):
    """Mirror of rangegp_proto::scan::ScanHeader (152 bytes, align 8)."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("point_count", ctypes.c_uint32),
        ("publisher_id", ctypes.c_uint64),
        ("sequence", ctypes.c_uint64),
        ("stamp_ns", ctypes.c_uint64),
        ("px_m", ctypes.c_double),
        ("py_m", ctypes.c_double),
        ("pz_m", ctypes.c_double),
        ("qx", ctypes.c_double),
        ("qy", ctypes.c_double),
        ("qz", ctypes.c_double),
        ("qw", ctypes.c_double),
        ("max_range_m", ctypes.c_double),
        ("range_noise_per_m", ctypes.c_double),
        # The sweep's twist in the sensor frame (all zero: a still sensor, nothing to deskew).
        ("vx_mps", ctypes.c_double),
        ("vy_mps", ctypes.c_double),
        ("vz_mps", ctypes.c_double),
        ("wx_radps", ctypes.c_double),
        ("wy_radps", ctypes.c_double),
        ("wz_radps", ctypes.c_double),
    ]

    @staticmethod
    def type_name() -> str:
        return "rangegp::ScanHeader"


class ScanPoint(ctypes.Structure):
    """Mirror of rangegp_proto::scan::ScanPoint (24 bytes, align 4)."""

    _fields_ = [
        ("range_m", ctypes.c_float),
        ("inclination_rad", ctypes.c_float),
        ("azimuth_rad", ctypes.c_float),
        ("ring", ctypes.c_uint16),
        ("column", ctypes.c_uint16),
        ("flags", ctypes.c_uint16),
        ("reserved", ctypes.c_uint16),
        # When the ray fired, ns after the header's stamp_ns (0: at the stamp).
        ("time_offset_ns", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        return "rangegp::ScanPoint"


assert ctypes.sizeof(ScanHeader) == 152 and ctypes.sizeof(ScanPoint) == 24


def flat_ground_scan(height: float, max_range: float) -> list:
    points = []
    for ring in range(16):
        elevation = math.radians(-15.0 + ring)
        inclination = math.pi / 2 - elevation
        for column in range(91):
            azimuth = math.radians(-90.0 + 2.0 * column)
            hit = height / math.sin(-elevation) if elevation < 0 else math.inf
            flags = FLAG_RING_COLUMN_VALID
            if hit >= max_range:
                flags |= FLAG_NO_RETURN
                hit = 0.0
            points.append(ScanPoint(hit, inclination, azimuth, ring, column, flags, 0))
    return points


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--service", default="rangegp/default/scans", help="iceoryx2 service name")
    ap.add_argument("--publisher-id", type=int, default=77)
    ap.add_argument("--sequence", type=int, default=1)
    ap.add_argument("--x", type=float, default=0.0)
    ap.add_argument("--y", type=float, default=0.0)
    ap.add_argument("--heading", type=float, default=0.0)
    ap.add_argument(
        "--linger",
        type=float,
        default=1.0,
        help="seconds to keep the publisher after sending: its samples vanish with it",
    )
    args = ap.parse_args()

    node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
    # The same quality of service as rangegp_proto::scan::open_scan_service.
    service = (
        node.service_builder(iox2.ServiceName.new(args.service))
        .publish_subscribe(iox2.Slice[ScanPoint])
        .user_header(ScanHeader)
        .max_publishers(16)
        .max_subscribers(4)
        .subscriber_max_buffer_size(8)
        .max_nodes(32)
        .history_size(0)
        .open_or_create()
    )
    points = flat_ground_scan(0.75, 10.0)
    publisher = service.publisher_builder().initial_max_slice_len(len(points)).create()

    sample = publisher.loan_slice_uninit(len(points))
    header = sample.user_header().contents
    header.protocol_version = PROTOCOL_VERSION
    header.point_count = len(points)
    header.publisher_id = args.publisher_id
    header.sequence = args.sequence
    header.stamp_ns = time.time_ns()
    header.px_m, header.py_m, header.pz_m = args.x, args.y, 0.75
    half = args.heading / 2.0
    header.qx, header.qy, header.qz, header.qw = 0.0, 0.0, math.sin(half), math.cos(half)
    header.max_range_m = 10.0
    header.range_noise_per_m = 0.0075 / 29.0
    payload = sample.payload()
    for i, point in enumerate(points):
        payload[i] = point
    sample.assume_init().send()
    print(f"published {len(points)} points as sequence {args.sequence} on {args.service}")
    # A sample lives in its publisher's data segment: a one-shot publisher that exits at once can
    # take it away before the daemon's next poll. A real driver runs on; this one waits a little.
    time.sleep(args.linger)
    return 0


if __name__ == "__main__":
    sys.exit(main())
