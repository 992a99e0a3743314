"""Scans to a rangegp daemon through iceoryx2 shared memory, from numpy arrays."""

from __future__ import annotations

import ctypes
import time
from typing import Any, Optional, Sequence

import iceoryx2 as iox2
import numpy as np

from .protocol import FLAG_NO_RETURN, POINT_DTYPE, PROTOCOL_VERSION, ScanHeader, ScanPoint


class ScanPublisher:
    """Publishes scans on a daemon's iceoryx2 scan service (``rangegp/<map_id>/scans`` by
    default), with the daemon's quality of service. Keep it alive while the daemon reads: a
    sample lives in its publisher's memory."""

    def __init__(self, service: str = "rangegp/default/scans", publisher_id: int = 77, max_points: int = 262144) -> None:
        self._node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
        self._service = (
            self._node.service_builder(iox2.ServiceName.new(service))
            .publish_subscribe(iox2.Slice[ScanPoint])
            .user_header(ScanHeader)
            .max_publishers(16)
            .max_subscribers(4)
            .subscriber_max_buffer_size(8)
            .max_nodes(32)
            .history_size(0)
            .open_or_create()
        )
        self._publisher = self._service.publisher_builder().initial_max_slice_len(max_points).create()
        self.publisher_id = publisher_id
        self.max_points = max_points
        self.sequence = 0

    def publish(
        self,
        ranges: Any,
        inclinations: Any,
        azimuths: Any,
        *,
        position: Sequence[float],
        orientation_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        max_range_m: float,
        range_noise_per_m: float = 0.001,
        stamp_ns: Optional[int] = None,
    ) -> int:
        """Sends one scan: rays in the sensor frame by inclination from +z in [0, π] and azimuth
        from +x in [−π, π] or [0, 2π) (radians), their ranges in metres (NaN, non-positive or
        beyond `max_range_m`: no return), and the sensor's pose in the map frame. Returns the
        scan's sequence number."""
        r = np.asarray(ranges, dtype=np.float64).ravel()
        inc = np.asarray(inclinations, dtype=np.float64).ravel()
        az = np.asarray(azimuths, dtype=np.float64).ravel()
        if not (len(r) == len(inc) == len(az)):
            raise ValueError("ranges, inclinations and azimuths must have the same length")
        if len(r) > self.max_points:
            raise ValueError(f"{len(r)} points exceed this publisher's {self.max_points}")
        if not (np.all(np.isfinite(inc)) and np.all(np.isfinite(az))):
            raise ValueError("every ray needs finite angles (a ray without a return too)")
        points = np.zeros(len(r), dtype=POINT_DTYPE)
        missing = ~np.isfinite(r) | (r <= 0.0) | (r >= max_range_m)
        points["range_m"] = np.where(missing, 0.0, r)
        points["inclination_rad"] = inc
        points["azimuth_rad"] = az
        points["flags"] = np.where(missing, FLAG_NO_RETURN, 0)
        self.sequence += 1
        sample = self._publisher.loan_slice_uninit(len(points))
        header = sample.user_header().contents
        header.protocol_version = PROTOCOL_VERSION
        header.point_count = len(points)
        header.publisher_id = self.publisher_id
        header.sequence = self.sequence
        header.stamp_ns = time.time_ns() if stamp_ns is None else int(stamp_ns)
        header.px_m, header.py_m, header.pz_m = (float(v) for v in position)
        header.qx, header.qy, header.qz, header.qw = (float(v) for v in orientation_xyzw)
        header.max_range_m = float(max_range_m)
        header.range_noise_per_m = float(range_noise_per_m)
        ctypes.memmove(sample.payload().data_ptr, points.ctypes.data, points.nbytes)
        sample.assume_init().send()
        return self.sequence

    def publish_xyz(self, xyz: Any, **kwargs: Any) -> int:
        """Sends one scan given as (N, 3) points in the sensor frame (x forward, y left, z up;
        NaN rows: no return); the keyword arguments are :meth:`publish`'s."""
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        r = np.linalg.norm(p, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            inc = np.arccos(np.clip(p[:, 2] / r, -1.0, 1.0))
        az = np.arctan2(p[:, 1], p[:, 0])
        # A row without a point has no direction: sent as a no-return straight ahead.
        return self.publish(np.where(r > 0, r, np.nan), np.nan_to_num(inc), np.nan_to_num(az), **kwargs)
