"""The rangegp Python package against a live daemon.

The daemon's endpoint, map id and scan service come from the environment (RANGEGP_CONNECT,
RANGEGP_MAP_ID, RANGEGP_SERVICE); the repository's `cargo test` starts a daemon and runs this
suite (tests/tests/python_interop.rs). A flat-ground scan is published with `ScanPublisher`,
then every query kind is asked with `Client`.
"""

import math
import os
import time

import numpy as np
import pytest

import rangegp

SENSOR = (2.0, -1.0, 0.75)
HEADING = 0.4
MAX_RANGE = 10.0


def flat_ground_rays():
    """The seed-000 scanner's rays (16 rings, -15..0 deg; 91 columns, -90..90 deg) over flat
    ground at z = 0 from 0.75 m: exact ranges, no return beyond 10 m."""
    elevations = np.radians(-15.0 + np.arange(16))
    azimuths = np.radians(-90.0 + 2.0 * np.arange(91))
    el, az = np.meshgrid(elevations, azimuths, indexing="ij")
    with np.errstate(divide="ignore"):
        ranges = np.where(el < 0, SENSOR[2] / np.sin(-el), np.inf)
    return ranges.ravel(), (math.pi / 2 - el).ravel(), az.ravel()


def pose():
    half = HEADING / 2.0
    return SENSOR, (0.0, 0.0, math.sin(half), math.cos(half))


@pytest.fixture(scope="module")
def env():
    keys = ("RANGEGP_CONNECT", "RANGEGP_MAP_ID", "RANGEGP_SERVICE")
    missing = [k for k in keys if k not in os.environ]
    if missing:
        pytest.fail(f"set {', '.join(missing)} to a live daemon's endpoint, map id and scan service")
    return {k: os.environ[k] for k in keys}


@pytest.fixture(scope="module")
def client(env):
    with rangegp.Client(connect=env["RANGEGP_CONNECT"], map_id=env["RANGEGP_MAP_ID"], timeout=20.0) as c:
        c.wait_for_daemon()
        yield c


def wait_accepted(client, count, timeout=20.0):
    deadline = time.monotonic() + timeout
    while client.status()["scans_accepted"] < count:
        assert time.monotonic() < deadline, f"the daemon did not accept {count} scans"
        time.sleep(0.02)


@pytest.fixture(scope="module")
def publisher(env, client):
    pub = rangegp.ScanPublisher(service=env["RANGEGP_SERVICE"], publisher_id=91, max_points=4096)
    position, orientation = pose()
    ranges, inclinations, azimuths = flat_ground_rays()
    pub.publish(
        ranges,
        inclinations,
        azimuths,
        position=position,
        orientation_xyzw=orientation,
        max_range_m=MAX_RANGE,
        range_noise_per_m=0.0075 / 29.0,
    )
    wait_accepted(client, 1)
    yield pub


def ahead(distance, lateral=0.0):
    """A map point `distance` ahead of the sensor and `lateral` to its left."""
    c, s = math.cos(HEADING), math.sin(HEADING)
    return [SENSOR[0] + distance * c - lateral * s, SENSOR[1] + distance * s + lateral * c]


def test_elevation_and_variance_are_arrays_with_nan_where_unobserved(client, publisher):
    answers = client.elevation(np.array([ahead(5.0), [40.0, 40.0]]))
    assert answers.z.shape == (2,)
    assert abs(answers.z[0]) < 0.01, answers
    assert answers.variance[0] > 0.0
    assert answers.source[0] == "window" and answers.source[1] == "none"
    assert math.isnan(answers.z[1]) and answers.refusal[1] == "unobserved"
    variance = client.variance([ahead(5.0), ahead(6.0, 1.0), [40.0, 40.0]])
    assert variance.shape == (3,) and np.all(variance[:2] > 0) and math.isnan(variance[2])


def test_grid_layers_come_as_2d_arrays_and_flat_ground_is_free(client, publisher):
    centre = ahead(5.0)
    grid = client.grid(
        (centre[0] - 1.0, centre[1] - 1.0),
        (centre[0] + 1.0, centre[1] + 1.0),
        0.1,
        layers=("slope", "slope_sigma", "risk", "cost"),
    )
    assert grid.elevation.shape == (20, 20)
    assert set(grid.layers) == {"slope", "slope_sigma", "risk"}
    slope = grid.layers["slope"]
    known = ~np.isnan(slope)
    assert known.sum() > 200, "most of the box lies in the scan's view"
    assert np.degrees(np.nanmax(slope)) < 2.0, "flat ground"
    assert grid.costmap.dtype == np.int8 and grid.costmap.shape == (20, 20)
    assert np.all(grid.costmap[known] >= 0) and np.all(grid.costmap[known] < 50)
    assert np.all(grid.costmap[~known] == -1)
    assert np.allclose(grid.centre(0, 0), grid.origin)
    assert grid.robot["max_slope_deg"] > 0


def test_point_slope_ray_and_view(client, publisher):
    s = client.slope([ahead(5.0)])
    assert np.degrees(s.slope[0]) < 2.0 and s.normal[0, 2] > 0.999
    assert 0.0 < s.resolution <= 0.3
    target = ahead(5.0)
    rays = client.ray([[target[0], target[1], 2.0]], [[0.0, 0.0, -1.0]], 10.0)
    assert abs(rays.range[0] - 2.0) < 0.02, rays
    assert abs(rays.hit_point[0, 2]) < 0.02 and rays.hit_probability[0] > 0.9
    position, orientation = pose()
    camera = {"lidar": {"ring_elevations_rad": [-0.2, -0.1], "columns": 36, "max_range_m": 10.0}}
    view = client.view(position, orientation, camera)
    assert view.range.shape == (2, 36)
    assert np.isfinite(view.range).any()


def test_refusals_raise_with_the_daemons_code(client, publisher):
    with pytest.raises(rangegp.RangegpError) as refused:
        client.grid((0.0, 0.0), (2.0, 2.0), 0.5, layers=("slope",))
    assert refused.value.code == "invalid_argument"
    with pytest.raises(ValueError):
        client.elevation([1.0, 2.0, 3.0])


def test_status_and_a_scan_given_as_xyz(client, publisher):
    before = client.status()
    assert before["version"] == rangegp.PROTOCOL_VERSION
    ranges, inclinations, azimuths = flat_ground_rays()
    ranges = np.where(np.isfinite(ranges), ranges, np.nan)
    xyz = np.stack(
        [
            ranges * np.sin(inclinations) * np.cos(azimuths),
            ranges * np.sin(inclinations) * np.sin(azimuths),
            ranges * np.cos(inclinations),
        ],
        axis=1,
    )
    position, orientation = pose()
    publisher.publish_xyz(
        xyz,
        position=position,
        orientation_xyzw=orientation,
        max_range_m=MAX_RANGE,
        range_noise_per_m=0.0075 / 29.0,
    )
    try:
        wait_accepted(client, before["scans_accepted"] + 1)
    except AssertionError:
        raise AssertionError(f"not accepted: {client.status()}")
    assert client.status()["scans_rejected"] == before["scans_rejected"]
