"""The shared geofence (safety service + mission checks): hand-worked distances and refusals."""
import math

import pytest

from aeroperception.services.lib.geofence import GEOFENCE_PARAMS, Geofence, GeofenceError, parse_polygon


def test_cylinder_and_ceiling_distances():
    g = Geofence.from_params(radius_m=100.0, max_altitude_m=50.0)
    assert g.distance_to_boundary_m(0, 0, 10) == pytest.approx(40.0)       # ceiling is nearer
    assert g.distance_to_boundary_m(60, 80, 10) == pytest.approx(0.0)      # on the wall (r = 100)
    assert g.distance_to_boundary_m(90, 0, 55) == pytest.approx(-5.0)      # above the ceiling


def test_polygon_inside_positive_outside_negative():
    g = Geofence.from_params(polygon=parse_polygon("0,0;10,0;10,10;0,10"))
    assert g.distance_to_boundary_m(5, 5, 3) == pytest.approx(5.0)
    assert g.distance_to_boundary_m(2, 5, 3) == pytest.approx(2.0)
    assert g.distance_to_boundary_m(13, 5, 3) == pytest.approx(-3.0)
    assert "polygon" in g.check_waypoint(13, 5, 3)


@pytest.mark.parametrize("wp, why", [
    ((0, 0, -50), "below the geofence floor"),
    ((10_000, 0, 5), "outside the geofence radius"),
    ((0, 0, 5000), "above the geofence ceiling"),
    ((math.nan, 0, 5), "not finite"),
])
def test_unsafe_waypoints_refused_with_reason(wp, why):
    assert why in Geofence.from_params().check_waypoint(*wp)


def test_reasonable_waypoint_accepted_and_params_build_the_fence():
    params = {p.name: p.default for p in GEOFENCE_PARAMS}
    g = Geofence.from_params(params)
    assert g.check_waypoint(20, -10, 5) is None
    assert g.radius_m == 500.0 and g.polygon == ()


@pytest.mark.parametrize("text", ["1,2;3,4", "a,b;c,d;e,f", "1,2,3;4,5;6,7"])
def test_bad_polygon_text_refused(text):
    with pytest.raises(GeofenceError):
        parse_polygon(text)
