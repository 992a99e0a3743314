"""The wire contract: the protocol version and ctypes mirrors of the shared-memory scan types
(rangegp-proto's `ScanHeader` and `ScanPoint`, byte for byte; docs/PROTOCOL.md)."""

import ctypes

import numpy as np

PROTOCOL_VERSION = 9
"""Version of the whole contract (scan layout and query messages)."""

FLAG_NO_RETURN = 1
"""`ScanPoint.flags`: the ray got no return (its range is ignored)."""
FLAG_RING_COLUMN_VALID = 2
"""`ScanPoint.flags`: `ring` and `column` are meaningful."""


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
        ("vx_mps", ctypes.c_double),
        ("vy_mps", ctypes.c_double),
        ("vz_mps", ctypes.c_double),
        ("wx_radps", ctypes.c_double),
        ("wy_radps", ctypes.c_double),
        ("wz_radps", ctypes.c_double),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name iceoryx2 matches against the daemon's."""
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
        ("time_offset_ns", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        """The type name iceoryx2 matches against the daemon's."""
        return "rangegp::ScanPoint"


POINT_DTYPE = np.dtype(
    [
        ("range_m", "<f4"),
        ("inclination_rad", "<f4"),
        ("azimuth_rad", "<f4"),
        ("ring", "<u2"),
        ("column", "<u2"),
        ("flags", "<u2"),
        ("reserved", "<u2"),
        ("time_offset_ns", "<u4"),
    ]
)
"""A numpy structured dtype laid out exactly as `ScanPoint` (copied into shared memory at once)."""

assert ctypes.sizeof(ScanHeader) == 152 and ctypes.sizeof(ScanPoint) == 24
assert POINT_DTYPE.itemsize == ctypes.sizeof(ScanPoint)
