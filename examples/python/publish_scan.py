#!/usr/bin/env python3
"""Publish one LiDAR scan to a rangegp daemon through iceoryx2 shared memory.

Needs the `rangegp` package (`pip install ./python`), whose `ScanPublisher` mirrors
rangegp-proto's `ScanHeader` and `ScanPoint` byte for byte (python/src/rangegp/protocol.py,
docs/PROTOCOL.md).

The scan is the seed-000 scanner (16 rings, -15..0 deg; 91 columns, -90..90 deg; 10 m)
looking at flat ground at z = 0 from `--x --y` at 0.75 m, heading `--heading` (radians):
ranges are exact, so the daemon's elevation there should come back as 0.

    python3 publish_scan.py --service rangegp/default/scans --x 0 --y 0
"""
import argparse
import math
import sys
import time

import numpy as np

import rangegp

HEIGHT = 0.75
MAX_RANGE = 10.0


def flat_ground_rays():
    """Ranges (inf: no return), inclinations and azimuths of the seed-000 scanner's rays."""
    elevations = np.radians(-15.0 + np.arange(16))
    azimuths = np.radians(-90.0 + 2.0 * np.arange(91))
    el, az = np.meshgrid(elevations, azimuths, indexing="ij")
    with np.errstate(divide="ignore"):
        ranges = np.where(el < 0, HEIGHT / np.sin(-el), np.inf)
    return ranges.ravel(), (math.pi / 2 - el).ravel(), az.ravel()


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
    ap.add_argument(
        "--until-stdin-closes",
        action="store_true",
        help="keep the publisher until stdin closes instead of --linger seconds "
        "(for a parent that knows when the daemon has taken the scan)",
    )
    args = ap.parse_args()

    publisher = rangegp.ScanPublisher(service=args.service, publisher_id=args.publisher_id, max_points=4096)
    publisher.sequence = args.sequence - 1
    ranges, inclinations, azimuths = flat_ground_rays()
    half = args.heading / 2.0
    sequence = publisher.publish(
        ranges,
        inclinations,
        azimuths,
        position=(args.x, args.y, HEIGHT),
        orientation_xyzw=(0.0, 0.0, math.sin(half), math.cos(half)),
        max_range_m=MAX_RANGE,
        range_noise_per_m=0.0075 / 29.0,
    )
    print(f"published {len(ranges)} points as sequence {sequence} on {args.service}", flush=True)
    # A sample lives in its publisher's data segment: a one-shot publisher that exits at once can
    # take it away before the daemon's next poll. A real driver runs on; this one waits until told
    # to go, or a little.
    if args.until_stdin_closes:
        sys.stdin.read()
    else:
        time.sleep(args.linger)
    return 0


if __name__ == "__main__":
    sys.exit(main())
