"""A world point's road, s, lane and distance to the road's edge on an OpenDRIVE road
(``adapters.road_position``), checked against the road's own lane starts
(``opendrive.lane_start``: the centre of a lane at s, computed forward from s and t) and
the lane widths of the files."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simserver.adapters.opendrive import lane_start, load_opendrive, profile_at
from simserver.adapters.road_position import RoadLocator
from simserver.testing import CONFIGS

ROADS = CONFIGS / "roads"


@pytest.mark.parametrize("name, road, lanes, widths, stations", [
    # crest-curve: border 2 (50 m), driving 1, driving -1 (3.2 m each), border -2 (30 m);
    # along the straight, the clothoid and over the crest
    ("crest-curve.xodr", "0", (-1, 1), {1: 3.2, 2: 50.0, -1: 3.2, -2: 30.0},
     (20.0, 150.0, 270.0, 390.0)),
    # velodrome: three 3 m lanes right of the line; on the straight, the clothoid (banking
    # up) and the 60 degree arc
    ("velodrome.xodr", "1", (-1, -2, -3), {-1: 3.0, -2: 3.0, -3: 3.0},
     (250.0, 550.0, 750.0, 1700.0)),
])
def test_lane_centres_come_back_as_their_lane_s_and_edge(name, road, lanes, widths,
                                                         stations):
    od = load_opendrive(ROADS / name)
    locator = RoadLocator(od)
    right = -sum(w for k, w in widths.items() if k < 0)
    left = sum(w for k, w in widths.items() if k > 0)
    for s in stations:
        for lane in lanes:
            x, y, _ = lane_start(od, road, s, lane)
            pos = locator.locate(x, y)
            inner = sum(widths[k] for k in widths if 0 < k * np.sign(lane) < abs(lane))
            t = np.sign(lane) * (inner + 0.5 * widths[lane])  # the lane's centre
            assert pos.road == road and pos.lane == lane
            assert pos.s_m == pytest.approx(s, abs=1e-6)
            assert pos.t_m == pytest.approx(t, abs=1e-6)
            assert pos.edge_m == pytest.approx(min(t - right, left - t), abs=1e-6)
            assert pos.on_road and pos.lane_type in ("driving", "border")
            # the surface under the point: elevation plus t sin(roll) up
            roll = profile_at(od.roads[0].superelevation, s)
            z = profile_at(od.roads[0].elevation, s) + t * math.sin(roll)
            assert pos.surface_z_m == pytest.approx(z, abs=1e-6)


def test_a_point_beyond_the_edge_is_off_the_road_by_its_distance():
    od = load_opendrive(ROADS / "crest-curve.xodr")
    locator = RoadLocator(od)
    # on the straight (heading +x, reference line y = 0): the right edge at y = -33.2
    pos = locator.locate(50.0, -40.0)
    assert not pos.on_road and pos.edge_m == pytest.approx(-6.8, abs=1e-9)
    assert pos.lane == -2 and pos.s_m == pytest.approx(50.0, abs=1e-9)
    pos = locator.locate(50.0, 60.0)  # left edge at y = +53.2
    assert not pos.on_road and pos.edge_m == pytest.approx(-6.8, abs=1e-9) and pos.lane == 2
    assert locator.locate(50.0, 5000.0) is None  # no road within reach
