"""Python peer of the rangegp terrain-mapping daemon (wire protocol 8).

- :class:`Client`: elevation, variance, ray, view, grid (planner layers), slope and status
  queries over Zenoh, numpy in and out.
- :class:`ScanPublisher`: scans to the daemon through iceoryx2 shared memory.
"""

from .client import Client, Elevation, Grid, RangegpError, Rays, Slope, View
from .protocol import PROTOCOL_VERSION, ScanHeader, ScanPoint
from .publisher import ScanPublisher

__all__ = [
    "Client",
    "Elevation",
    "Grid",
    "PROTOCOL_VERSION",
    "RangegpError",
    "Rays",
    "ScanHeader",
    "ScanPoint",
    "ScanPublisher",
    "Slope",
    "View",
]
