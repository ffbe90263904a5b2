"""Share of track points with a point of another track within R px in the same frame (duplicate tracks of one
vehicle show up here): python scripts/track_crowding.py out/track/tracks.txt [--radius 6]."""

import argparse

import numpy as np
from scipy.spatial import cKDTree

p = argparse.ArgumentParser(description=__doc__)
p.add_argument("tracks")
p.add_argument("--radius", type=float, default=6.0)
a = p.parse_args()
rows = np.loadtxt(a.tracks, delimiter=",", ndmin=2)
crowded = 0
for f in np.unique(rows[:, 0]):
    r = rows[rows[:, 0] == f]
    xy = r[:, 2:4] + r[:, 4:6] / 2
    pairs = cKDTree(xy).query_pairs(a.radius, output_type="ndarray")
    pairs = pairs[r[pairs[:, 0], 1] != r[pairs[:, 1], 1]]
    crowded += len(np.unique(pairs))
print(f"{crowded} of {len(rows)} track points ({100 * crowded / max(1, len(rows)):.2f} %) have another track "
      f"within {a.radius:g} px")
