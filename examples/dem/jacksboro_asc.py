"""Writes the Jacksboro fault DEM that matplotlib ships as sample data as an ESRI ASCII grid.

Real geography for `rangegp-eval calibration --dem` and `layers --dem` (docs/EVALUATION.md,
"Real geography"): 344 x 403 elevations (metres) at 3 arc-seconds, Tennessee. Its cells are
74.5 m east-west and 92.8 m north-south, so the rows are resampled (linearly) to square 74.5 m
cells. Needs numpy and matplotlib:

    python3 -m venv target/dem-venv
    target/dem-venv/bin/pip install numpy matplotlib
    target/dem-venv/bin/python examples/dem/jacksboro_asc.py target/jacksboro.asc
"""

import math
import sys

import numpy as np
from matplotlib import cbook

EARTH_M_PER_DEGREE = 111_320.0
LATITUDE_DEG = 36.59


def main(out: str) -> None:
    with cbook.get_sample_data("jacksboro_fault_dem.npz") as dem:
        z = dem["elevation"].astype(float)
        cell_x = float(dem["dx"]) * EARTH_M_PER_DEGREE * math.cos(math.radians(LATITUDE_DEG))
        cell_y = float(dem["dy"]) * EARTH_M_PER_DEGREE
    rows = int(round((z.shape[0] - 1) * cell_y / cell_x)) + 1
    at = np.linspace(0.0, z.shape[0] - 1, rows)
    square = np.stack([np.interp(at, np.arange(z.shape[0]), z[:, c]) for c in range(z.shape[1])], axis=1)
    with open(out, "w", encoding="ascii") as f:
        f.write(f"ncols {square.shape[1]}\nnrows {square.shape[0]}\n")
        f.write(f"xllcorner 0\nyllcorner 0\ncellsize {cell_x:.3f}\nNODATA_value -9999\n")
        for row in square:
            f.write(" ".join(f"{v:.2f}" for v in row) + "\n")
    print(f"{out}: {square.shape[1]} x {square.shape[0]} cells of {cell_x:.3f} m")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: jacksboro_asc.py OUT.asc")
    main(sys.argv[1])
