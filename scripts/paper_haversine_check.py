"""Recompute the paper's Table 3 inaccuracies from the coordinates printed in its Tables 2 and 3.

Prints the Haversine distances computed correctly and with latitude and longitude
swapped. The swapped version reproduces the paper's numbers to rounding, which
suggests the paper's errors overstate east-west distances by 1/cos(49 deg) = 1.52.

    .venv/bin/python scripts/paper_haversine_check.py [--json PATH]
"""

import json
import sys

import numpy as np

from visloc.geo import haversine_distance_m

# (lon, lat) as printed in the paper, steps t-5 .. t
BEST_MATCH = [(8.43413, 49.01494), (8.43429, 49.01500), (8.43413, 49.01494), (8.43398, 49.01489), (8.43384, 49.01484), (8.43369, 49.01479)]
ACTUAL = [(8.43429, 49.01500), (8.43413, 49.01494), (8.43398, 49.01489), (8.43384, 49.01484), (8.43369, 49.01479), (8.43355, 49.01475)]
ESTIMATE = [(8.43412, 49.01493), (8.43445, 49.01506), (8.43408, 49.01492), (8.43387, 49.01485), (8.43371, 49.01479), (8.43355, 49.01474)]
PAPER_MEASUREMENT_M = [18.99, 18.99, 17.57, 16.52, 17.57, 16.19]
PAPER_ESTIMATE_M = [19.81, 38.77, 11.52, 3.28, 2.31, 0.94]


def distances(points, swapped):
    lon, lat = np.array(points).T
    tlon, tlat = np.array(ACTUAL).T
    if swapped:  # latitude where longitude belongs and vice versa
        return haversine_distance_m(lon, lat, tlon, tlat)
    return haversine_distance_m(lat, lon, tlat, tlon)


def main(argv: list[str]) -> int:
    fmt = lambda v: " ".join(f"{x:7.2f}" for x in v)  # noqa: E731
    print(" " * 50 + " ".join(f"{s:>7}" for s in ["t-5", "t-4", "t-3", "t-2", "t-1", "t"]))
    result = {}
    for name, points, paper in (("measurement", BEST_MATCH, PAPER_MEASUREMENT_M), ("estimate", ESTIMATE, PAPER_ESTIMATE_M)):
        swapped, correct = distances(points, True), distances(points, False)
        print(f"{name + ' error, paper (m)':50}{fmt(paper)}")
        print(f"{name + ' error, Haversine lat/lon swapped (m)':50}{fmt(swapped)}")
        print(f"{name + ' error, Haversine correct (m)':50}{fmt(correct)}")
        result[name] = {"paper_m": paper, "swapped_m": swapped.tolist(), "correct_m": correct.tolist()}
    if argv[:1] == ["--json"] and len(argv) == 2:
        with open(argv[1], "w") as fh:
            json.dump(result, fh, indent=1)
        print(f"wrote {argv[1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
