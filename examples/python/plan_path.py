#!/usr/bin/env python3
"""Plan a path over a rangegp daemon's cost layer: A* on the ROS-style costmap of a grid query.

Needs the `rangegp` package (`pip install ./python`). Asks for the `traversal_cost` and `cost`
layers over a box, plans 8-connected from START to GOAL through cells that are known and not
lethal (costmap 0-99; -1 unknown and 100 lethal are walls), each step as long as it is times
1 + 10 x the traversal cost of the cells it joins, and prints the path as JSON on stdout.

    python3 plan_path.py --connect tcp/127.0.0.1:7447 --bbox 0 -5 10 5 --res 0.1 \\
        --start 1 0 --goal 9 2
"""
import argparse
import heapq
import json
import math
import sys

import numpy as np

import rangegp

RISK_WEIGHT = 10.0


def astar(costmap: np.ndarray, cost: np.ndarray, start, goal):
    """The cheapest 8-connected list of (col, row) cells from start to goal, or None; `costmap`
    and `cost` are indexed [row, col]."""
    rows, cols = costmap.shape

    def free(c, r):
        return 0 <= c < cols and 0 <= r < rows and 0 <= costmap[r, c] < 100

    def weight(c, r):
        return 1.0 + RISK_WEIGHT * np.nan_to_num(cost[r, c])

    def octile(c, r):
        dx, dy = abs(c - goal[0]), abs(r - goal[1])
        return max(dx, dy) - min(dx, dy) + math.sqrt(2.0) * min(dx, dy)

    if not (free(*start) and free(*goal)):
        return None
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
                if n == cell or not free(*n):
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

    with rangegp.Client(connect=args.connect, map_id=args.map_id, timeout=args.timeout) as client:
        try:
            client.wait_for_daemon()
            grid = client.grid(args.bbox[:2], args.bbox[2:], args.res, layers=("traversal_cost", "cost"))
        except rangegp.RangegpError as e:
            print(e, file=sys.stderr)
            return 2 if e.code == "timeout" else 1
    rows, cols = grid.costmap.shape

    def cell_of(x, y):
        c, r = np.rint((np.array([x, y]) - grid.origin) / grid.resolution).astype(int)
        return (int(c), int(r)) if 0 <= c < cols and 0 <= r < rows else None

    start, goal = cell_of(*args.start), cell_of(*args.goal)
    if start is None or goal is None:
        print("start or goal lies outside the box", file=sys.stderr)
        return 1
    path = astar(grid.costmap, grid.layers["traversal_cost"], start, goal)
    if path is None:
        print("no path through known, non-lethal cells", file=sys.stderr)
        return 3
    points = [grid.centre(c, r).tolist() for c, r in path]
    length = sum(math.dist(a, b) for a, b in zip(points, points[1:]))
    max_cost = max(int(grid.costmap[r, c]) for c, r in path)
    print(json.dumps({"path_m": points, "length_m": length, "max_cost": max_cost, "cells": len(path)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
