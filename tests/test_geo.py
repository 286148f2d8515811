"""Geodesy against distances known independently of pyproj."""

import math

import numpy as np
import pytest

from visloc.geo import LocalFrame, geodesic_distance_m, haversine_distance_m, yaw_enu_to_heading_deg
from visloc.params import METRES_PER_DEGREE


def test_one_degree_of_latitude_at_the_equator_on_wgs84():
    # meridian arc 0..1 deg on WGS84: 110 574.389 m (standard tables)
    assert geodesic_distance_m(0.0, 0.0, 1.0, 0.0) == pytest.approx(110_574.389, abs=0.01)


def test_one_degree_of_longitude_at_the_equator_on_wgs84():
    # equatorial arc = a * pi / 180 with a = 6 378 137 m
    assert geodesic_distance_m(0.0, 0.0, 0.0, 1.0) == pytest.approx(6_378_137 * math.pi / 180, abs=0.01)


def test_haversine_is_the_mean_sphere_great_circle():
    assert haversine_distance_m(0.0, 0.0, 1.0, 0.0) == pytest.approx(METRES_PER_DEGREE, rel=1e-12)
    assert haversine_distance_m(0.0, 0.0, 0.0, 180.0) == pytest.approx(math.pi * 6_371_008.8, rel=1e-12)


def test_distances_broadcast_and_are_zero_on_the_diagonal():
    lat = np.array([49.0, 49.001, 49.002])
    d = geodesic_distance_m(lat, 8.43, lat, 8.43)
    assert d.shape == (3,) and np.all(d == 0)


def test_geodesic_and_haversine_agree_to_half_a_percent_over_a_drive():
    a, b = (49.015003823272, 8.4342971002335), (49.014596344219, 8.4329721922397)
    g, h = geodesic_distance_m(*a, *b), haversine_distance_m(*a, *b)
    assert g == pytest.approx(106.99, abs=0.01)
    assert abs(g - h) / g < 0.005


def test_local_frame_axes_and_round_trip():
    frame = LocalFrame(49.0, 8.4)
    east_north = frame.to_local([49.0, 49.001, 49.0], [8.4, 8.4, 8.401])
    np.testing.assert_allclose(east_north[0], [0, 0], atol=1e-9)
    assert east_north[1, 0] == pytest.approx(0, abs=1e-6) and east_north[1, 1] == pytest.approx(111.2, abs=0.1)
    assert east_north[2, 1] == pytest.approx(0, abs=0.01) and east_north[2, 0] == pytest.approx(73.1, abs=0.1)
    lat, lon = frame.to_geo(east_north)
    np.testing.assert_allclose(lat, [49.0, 49.001, 49.0], atol=1e-12)
    np.testing.assert_allclose(lon, [8.4, 8.4, 8.401], atol=1e-12)
    # local distances equal geodesic ones within a millimetre at this range
    assert np.hypot(*east_north[2]) == pytest.approx(geodesic_distance_m(49.0, 8.4, 49.0, 8.401), abs=1e-3)


def test_a_geotag_micrometres_from_the_origin_keeps_its_offset():
    """Drive 0001's two cameras' first geotags lie 15 micrometres apart (their images 1.2 us apart): the local
    frame of one places the other there, and back, where PROJ's aeqd snaps points within 0.6 mm onto the origin."""
    frame = LocalFrame(49.01500361489051, 8.434296575797951)
    east_north = frame.to_local(49.01500361496352, 8.434296575981705)
    assert 5e-6 < np.hypot(*east_north) < 5e-5
    lat, lon = frame.to_geo(east_north)
    assert (float(lat), float(lon)) == pytest.approx((49.01500361496352, 8.434296575981705), abs=1e-13)
    np.testing.assert_allclose(frame.to_local(frame.origin_lat_deg, frame.origin_lon_deg), [0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("yaw_rad,heading_deg", [(0.0, 90.0), (math.pi / 2, 0.0), (-math.pi / 2, 180.0), (math.pi, 270.0)])
def test_kitti_yaw_to_compass_heading(yaw_rad, heading_deg):
    assert yaw_enu_to_heading_deg(yaw_rad) == pytest.approx(heading_deg)
