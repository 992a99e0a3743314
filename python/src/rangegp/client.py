"""Queries to a rangegp daemon over Zenoh (JSON payloads), numpy in and out."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any, Dict, Iterable, Mapping, Optional, Sequence

import numpy as np
import zenoh

from .protocol import PROTOCOL_VERSION


class RangegpError(RuntimeError):
    """The daemon refused a request (`code` is its error code, e.g. ``invalid_argument``), or no
    reply came within the timeout (`code` ``timeout``)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def _floats(values: Iterable[Optional[float]]) -> np.ndarray:
    """A float64 array with NaN where the wire said null."""
    return np.array([np.nan if v is None else v for v in values], dtype=np.float64)


def _points(points: Any) -> list:
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"points must be an (N, 2) array of map (x, y), got shape {array.shape}")
    return array.tolist()


@dataclass
class Elevation:
    """Elevation answers, one entry per point asked."""

    z: np.ndarray
    """Surface height, metres (NaN where refused)."""
    variance: np.ndarray
    """Variance of `z`, m² (latent surface)."""
    source: np.ndarray
    """``window``, ``aggregate`` or ``none`` per point."""
    provenance: np.ndarray
    """``observed``, ``interpolated``, ``extrapolated`` or ``none`` per point."""
    refusal: np.ndarray
    """Why a point has no value (``unobserved``, ``too_uncertain``), else None."""


@dataclass
class Rays:
    """Ray answers, one entry per ray."""

    range: np.ndarray
    """Expected distance to the surface, metres (NaN without a hit)."""
    range_variance: np.ndarray
    """Variance of `range`, m²."""
    hit_probability: np.ndarray
    """P(the ray meets the surface before its max range); NaN where nothing is known."""
    hit_point: np.ndarray
    """(N, 3) expected hit points in the map frame, metres."""
    source: np.ndarray
    """Which map answered, per ray."""


@dataclass
class View:
    """A range image (rows × cols) of the map as a sensor would see it."""

    range: np.ndarray
    sigma: np.ndarray
    hit_probability: np.ndarray


@dataclass
class Grid:
    """Grid layers as (rows, cols) arrays indexed [row, col] from the lower-left cell."""

    origin: np.ndarray
    """Centre (x, y) of cell (0, 0), metres."""
    resolution: float
    elevation: np.ndarray
    variance: np.ndarray
    layers: Dict[str, np.ndarray]
    """Derived layers asked for, by wire name (``slope``, ``risk``, ...)."""
    costmap: Optional[np.ndarray]
    """ROS OccupancyGrid int8 values (0–100, 100 lethal, −1 unknown) when ``cost`` was asked."""
    robot: Dict[str, float]
    """The robot model the layers judged by."""

    def centre(self, col: int, row: int) -> np.ndarray:
        """Map (x, y) of the centre of cell (col, row)."""
        return self.origin + np.array([col, row], dtype=np.float64) * self.resolution


@dataclass
class Slope:
    """Slope answers, one entry per point asked."""

    slope: np.ndarray
    """Slope angle over the robot's footprint, radians."""
    slope_sigma: np.ndarray
    aspect: np.ndarray
    normal: np.ndarray
    """(N, 3) unit normals."""
    slope_risk: np.ndarray
    resolution: float
    """Resolution the footprint was sampled at, metres."""


class Client:
    """A session to one daemon's map: ``Client(connect=..., map_id=...)``; use as a context manager
    or call :meth:`close`. Every call waits at most `timeout` seconds."""

    def __init__(
        self,
        connect: str | Sequence[str] = "tcp/127.0.0.1:7447",
        map_id: str = "default",
        timeout: float = 10.0,
    ) -> None:
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps(endpoints))
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        self._session = zenoh.open(conf)
        self.map_id = map_id
        self.timeout = timeout

    def close(self) -> None:
        """Closes the Zenoh session."""
        self._session.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_for_daemon(self, timeout: Optional[float] = None) -> None:
        """Waits (bounded) until the daemon's liveliness token is routed here; raises
        :class:`RangegpError` ``timeout`` otherwise."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        alive = f"rangegp/{self.map_id}/@alive"
        while not any(r.ok for r in self._session.liveliness().get(alive, timeout=0.5)):
            if time.monotonic() > deadline:
                raise RangegpError("timeout", f"no daemon for map {self.map_id!r}")
            time.sleep(0.02)

    def _call(self, key: str, request: Mapping[str, Any]) -> Dict[str, Any]:
        replies = self._session.get(
            f"rangegp/{self.map_id}/{key}",
            payload=json.dumps(request),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            target=zenoh.QueryTarget.ALL_COMPLETE,
            timeout=self.timeout,
        )
        for reply in replies:
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_string())
            error = json.loads(reply.err.payload.to_string())
            raise RangegpError(error.get("code", "unknown"), error.get("message", ""))
        raise RangegpError("timeout", f"no reply to {key} within {self.timeout} s")

    def elevation(self, points: Any) -> Elevation:
        """Elevation at (N, 2) map points."""
        items = self._call("query/elevation", {"version": PROTOCOL_VERSION, "points": _points(points)})["items"]
        return Elevation(
            z=_floats(i["z_m"] for i in items),
            variance=_floats(i["z_var_m2"] for i in items),
            source=np.array([i["source"] for i in items], dtype=object),
            provenance=np.array([i["provenance"] for i in items], dtype=object),
            refusal=np.array([i["refusal"] for i in items], dtype=object),
        )

    def variance(self, points: Any) -> np.ndarray:
        """Elevation variance (m², NaN where refused) at (N, 2) map points."""
        items = self._call("query/variance", {"version": PROTOCOL_VERSION, "points": _points(points)})["items"]
        return _floats(i["z_var_m2"] for i in items)

    def ray(self, origins: Any, directions: Any, max_range_m: Any = 20.0) -> Rays:
        """Casts (N, 3) rays from `origins` along `directions` (map frame) up to `max_range_m`
        (one value or one per ray)."""
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        m = np.broadcast_to(np.asarray(max_range_m, dtype=np.float64), (len(o),))
        if len(d) != len(o):
            raise ValueError("origins and directions must have the same length")
        rays = [{"origin_m": a.tolist(), "direction": b.tolist(), "max_range_m": float(r)} for a, b, r in zip(o, d, m)]
        items = self._call("query/ray", {"version": PROTOCOL_VERSION, "rays": rays})["items"]
        hit = np.array([i["hit_point_m"] or [np.nan] * 3 for i in items], dtype=np.float64).reshape(-1, 3)
        return Rays(
            range=_floats(i["range_m"] for i in items),
            range_variance=_floats(i["range_var_m2"] for i in items),
            hit_probability=_floats(i["hit_probability"] for i in items),
            hit_point=hit,
            source=np.array([i["source"] for i in items], dtype=object),
        )

    def view(self, position: Sequence[float], orientation_xyzw: Sequence[float], camera: Mapping[str, Any]) -> View:
        """A range image from a pose; `camera` as on the wire, e.g. ``{"lidar":
        {"ring_elevations_rad": [...], "columns": 360, "max_range_m": 30.0}}``."""
        request = {
            "version": PROTOCOL_VERSION,
            "position_m": [float(v) for v in position],
            "orientation_xyzw": [float(v) for v in orientation_xyzw],
            "camera": dict(camera),
        }
        rep = self._call("query/view", request)
        shape = (rep["rows"], rep["cols"])
        return View(
            range=_floats(rep["range_m"]).reshape(shape),
            sigma=_floats(rep["sigma_m"]).reshape(shape),
            hit_probability=_floats(rep["hit_probability"]).reshape(shape),
        )

    def grid(
        self,
        min_m: Sequence[float],
        max_m: Sequence[float],
        resolution_m: float,
        layers: Sequence[str] = (),
        robot: Optional[Mapping[str, float]] = None,
    ) -> Grid:
        """Elevation and variance over the box, and the planner `layers` named (wire names:
        ``slope``, ``slope_sigma``, ``aspect``, ``roughness``, ``roughness_sigma``, ``step``,
        ``step_sigma``, ``slope_risk``, ``step_risk``, ``unknown_risk``, ``risk``,
        ``traversal_cost``, ``cost``) for `robot` (``None``: the daemon's)."""
        request: Dict[str, Any] = {
            "version": PROTOCOL_VERSION,
            "min_m": [float(v) for v in min_m],
            "max_m": [float(v) for v in max_m],
            "resolution_m": float(resolution_m),
            "layers": list(layers),
            "robot": dict(robot) if robot is not None else None,
        }
        rep = self._call("query/grid", request)
        shape = (rep["rows"], rep["cols"])
        costmap = np.array(rep["costmap"], dtype=np.int8).reshape(shape) if "cost" in layers else None
        return Grid(
            origin=np.array(rep["origin_m"], dtype=np.float64),
            resolution=float(rep["resolution_m"]),
            elevation=_floats(rep["elevation_m"]).reshape(shape),
            variance=_floats(rep["variance_m2"]).reshape(shape),
            layers={l["layer"]: _floats(l["values"]).reshape(shape) for l in rep["layers"]},
            costmap=costmap,
            robot=rep["robot"],
        )

    def slope(self, points: Any, robot: Optional[Mapping[str, float]] = None) -> Slope:
        """Slope with σ, aspect, normal and slope risk at (N, 2) map points."""
        request = {
            "version": PROTOCOL_VERSION,
            "points": _points(points),
            "robot": dict(robot) if robot is not None else None,
        }
        rep = self._call("query/slope", request)
        items = rep["items"]
        return Slope(
            slope=_floats(i["slope_rad"] for i in items),
            slope_sigma=_floats(i["slope_sigma_rad"] for i in items),
            aspect=_floats(i["aspect_rad"] for i in items),
            normal=np.array([i["normal"] or [np.nan] * 3 for i in items], dtype=np.float64).reshape(-1, 3),
            slope_risk=_floats(i["slope_risk"] for i in items),
            resolution=float(rep["resolution_m"]),
        )

    def status(self) -> Dict[str, Any]:
        """The daemon's status (counters, latency percentiles, memory) as a dict."""
        return self._call("status", {"version": PROTOCOL_VERSION})
