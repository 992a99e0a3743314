#!/usr/bin/env python3
"""Plan a path over a rangegp daemon's cost layer: A* on the ROS-style costmap of a grid query.

Needs only `pip install eclipse-zenoh==1.10.2`. Asks `query/grid` (JSON) for the `traversal_cost`
and `cost` layers over a box, plans 8-connected from START to GOAL through cells that are known
and not lethal (costmap 0-99; -1 unknown and 100 lethal are walls), each step as long as it is
times 1 + 10 x the traversal cost of the cells it joins, and prints the path as JSON on stdout.

    python3 plan_path.py --connect tcp/127.0.0.1:7447 --bbox 0 -5 10 5 --res 0.1 \\
        --start 1 0 --goal 9 2
"""
import argparse
import heapq
import json
import math
import sys
import time

import zenoh

PROTOCOL_VERSION = 8
RISK_WEIGHT = 10.0


def query_grid(session, map_id, bbox, res, timeout):
    """The grid reply (a dict), or raises RuntimeError with the daemon's refusal."""
    request = {
        "version": PROTOCOL_VERSION,
        "min_m": [bbox[0], bbox[1]],
        "max_m": [bbox[2], bbox[3]],
        "resolution_m": res,
        "layers": ["traversal_cost", "cost"],
    }
    replies = session.get(
        f"rangegp/{map_id}/query/grid",
        payload=json.dumps(request),
        encoding=zenoh.Encoding.APPLICATION_JSON,
        target=zenoh.QueryTarget.ALL_COMPLETE,
        timeout=timeout,
    )
    for reply in replies:
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_string())
        error = json.loads(reply.err.payload.to_string())
        raise RuntimeError(f"daemon refused the grid: {error['code']}: {error['message']}")
    raise RuntimeError("no grid reply within the timeout")


def cell_of(grid, x, y):
    """(col, row) of the cell holding map point (x, y), or None outside the grid."""
    res = grid["resolution_m"]
    col = round((x - grid["origin_m"][0]) / res)
    row = round((y - grid["origin_m"][1]) / res)
    if 0 <= col < grid["cols"] and 0 <= row < grid["rows"]:
        return col, row
    return None


def astar(grid, start, goal):
    """The cheapest 8-connected list of cells from start to goal, or None."""
    cols, rows = grid["cols"], grid["rows"]
    costmap = grid["costmap"]
    cost = next(l["values"] for l in grid["layers"] if l["layer"] == "traversal_cost")

    def free(c, r):
        value = costmap[r * cols + c]
        return 0 <= value < 100

    def weight(c, r):
        return 1.0 + RISK_WEIGHT * (cost[r * cols + c] or 0.0)

    if not (free(*start) and free(*goal)):
        return None

    def octile(c, r):
        dx, dy = abs(c - goal[0]), abs(r - goal[1])
        return max(dx, dy) - min(dx, dy) + math.sqrt(2.0) * min(dx, dy)

    best = {start: 0.0}
    came = {}
    frontier = [(octile(*start), 0.0, start)]
    while frontier:
        _, g, cell = heapq.heappop(frontier)
        if cell == goal:
            path = [cell]
            while cell in came:
                cell = came[cell]
                path.append(cell)
            return path[::-1]
        if g > best.get(cell, math.inf):
            continue
        c, r = cell
        for dc in (-1, 0, 1):
            for dr in (-1, 0, 1):
                n = (c + dc, r + dr)
                if n == cell or not (0 <= n[0] < cols and 0 <= n[1] < rows) or not free(*n):
                    continue
                step = math.sqrt(2.0) if dc and dr else 1.0
                ng = g + step * 0.5 * (weight(c, r) + weight(*n))
                if ng < best.get(n, math.inf):
                    best[n] = ng
                    came[n] = cell
                    heapq.heappush(frontier, (ng + octile(*n), ng, n))
    return None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="daemon endpoint")
    ap.add_argument("--map-id", default="default")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds")
    ap.add_argument("--bbox", type=float, nargs=4, required=True, metavar=("X0", "Y0", "X1", "Y1"))
    ap.add_argument("--res", type=float, default=0.1, help="cell side, metres")
    ap.add_argument("--start", type=float, nargs=2, required=True, metavar=("X", "Y"))
    ap.add_argument("--goal", type=float, nargs=2, required=True, metavar=("X", "Y"))
    args = ap.parse_args()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        deadline = time.monotonic() + args.timeout
        alive = f"rangegp/{args.map_id}/@alive"
        while not any(r.ok for r in session.liveliness().get(alive, timeout=0.5)):
            if time.monotonic() > deadline:
                print(f"no rangegp daemon for map {args.map_id!r} at {args.connect}", file=sys.stderr)
                return 2
        try:
            grid = query_grid(session, args.map_id, args.bbox, args.res, args.timeout)
        except RuntimeError as e:
            print(e, file=sys.stderr)
            return 1
    start, goal = cell_of(grid, *args.start), cell_of(grid, *args.goal)
    if start is None or goal is None:
        print("start or goal lies outside the box", file=sys.stderr)
        return 1
    path = astar(grid, start, goal)
    if path is None:
        print("no path through known, non-lethal cells", file=sys.stderr)
        return 3
    res, origin = grid["resolution_m"], grid["origin_m"]
    points = [[origin[0] + c * res, origin[1] + r * res] for c, r in path]
    length = sum(math.dist(a, b) for a, b in zip(points, points[1:]))
    costs = [grid["costmap"][r * grid["cols"] + c] for c, r in path]
    print(json.dumps({"path_m": points, "length_m": length, "max_cost": max(costs), "cells": len(path)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
