#!/usr/bin/env python3
"""Ask a rangegp daemon for elevation at (x, y) points over Zenoh, with JSON payloads.

Needs only `pip install eclipse-zenoh==1.10.2`. Prints the daemon's JSON reply on stdout.

    python3 query_elevation.py --connect tcp/127.0.0.1:7447 --map-id default 3.0 1.5 4.0 -2.0
"""
import argparse
import json
import sys
import time

import zenoh

PROTOCOL_VERSION = 9


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="daemon endpoint")
    ap.add_argument("--map-id", default="default")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds")
    ap.add_argument("coords", type=float, nargs="+", help="x1 y1 [x2 y2 ...] in the map frame, metres")
    args = ap.parse_args()
    if len(args.coords) % 2:
        ap.error("coordinates come in (x, y) pairs")
    points = [[args.coords[i], args.coords[i + 1]] for i in range(0, len(args.coords), 2)]

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        # Wait (bounded) until the daemon's liveliness token is routed to us.
        deadline = time.monotonic() + args.timeout
        alive = f"rangegp/{args.map_id}/@alive"
        while not any(r.ok for r in session.liveliness().get(alive, timeout=0.5)):
            if time.monotonic() > deadline:
                print(f"no rangegp daemon for map {args.map_id!r} at {args.connect}", file=sys.stderr)
                return 2
        request = {"version": PROTOCOL_VERSION, "points": points}
        replies = session.get(
            f"rangegp/{args.map_id}/query/elevation",
            payload=json.dumps(request),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            target=zenoh.QueryTarget.ALL_COMPLETE,
            timeout=args.timeout,
        )
        for reply in replies:
            if reply.ok is not None:
                print(reply.ok.payload.to_string())
                return 0
            error = json.loads(reply.err.payload.to_string())
            print(f"daemon refused the query: {error['code']}: {error['message']}", file=sys.stderr)
            return 1
    print("no reply within the timeout", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
