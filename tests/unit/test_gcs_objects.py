"""gcs: tracked objects reach ground stations -- a STATUSTEXT naming each new and each lost object
with where it is, and every confirmed object as an ADS-B contact (QGC / Mission Planner draw it on
the map by callsign) refreshed at 1 Hz, never an uploaded plan item."""
from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import common as M

from aeroperception.schemas import Header, ObjectEvent, TrackedObject, TrackedObjectArray, Vector3
from aeroperception.services.gcs.messages import statustext
from aeroperception.services.gcs.objects_relay import ObjectsRelay, adsb_contact, callsign, event_text


def person(track_id=7, confirmed=True, geo=True, **kw) -> TrackedObject:
    return TrackedObject(track_id=track_id, class_name="person", class_id=0, confirmed=confirmed,
                         position_m=Vector3(x=12.3, y=4.1, z=0.9), velocity_mps=Vector3(x=1.0, y=1.0, z=0.0),
                         best_score=0.91, hits=5, latitude_deg=47.3981234 if geo else None,
                         longitude_deg=8.5457321 if geo else None, altitude_amsl_m=489.5 if geo else None, **kw)


def test_new_and_lost_objects_are_told_with_their_position():
    sev, text = event_text(ObjectEvent(event=ObjectEvent.CONFIRMED, object=person()))
    assert sev == M.MAV_SEVERITY_NOTICE and text == "Object: person #7 at 47.398123, 8.545732 (0.91)"
    sev, text = event_text(ObjectEvent(event=ObjectEvent.LOST, object=person(geo=False)))
    assert sev == M.MAV_SEVERITY_INFO and text == "Object: person #7 lost at E 12.3 N 4.1 m"
    assert event_text(ObjectEvent(event=ObjectEvent.REACQUIRED, object=person()))[1] == \
        "Object: person #7 seen again at 47.398123, 8.545732"
    assert event_text(ObjectEvent(event="renamed", object=person())) is None
    # Over MAVLink: fits one STATUSTEXT (50 characters) or goes out in chunks that reassemble.
    msgs = statustext(M.MAV_SEVERITY_NOTICE, text, 3)
    assert b"".join(m.text if isinstance(m.text, bytes) else m.text.encode() for m in msgs).decode() == text


def test_a_confirmed_object_is_an_adsb_point_obstacle_labelled_by_class_and_id():
    m = adsb_contact(person())
    mav = M.MAVLink(None, srcSystem=1, srcComponent=1)
    back = mav.decode(bytearray(m.pack(mav)))                                 # a valid message on the wire
    assert back.get_type() == "ADSB_VEHICLE"
    assert (back.lat, back.lon, back.altitude) == (473981234, 85457321, 489500)
    assert back.callsign.rstrip("\x00") == "PERSON7" and back.ICAO_address == 0xAE0007
    assert back.emitter_type == M.ADSB_EMITTER_TYPE_POINT_OBSTACLE
    assert back.altitude_type == M.ADSB_ALTITUDE_TYPE_GEOMETRIC
    assert back.heading == 4500 and back.hor_velocity == 141               # north-east at 1.41 m/s
    assert back.flags & M.ADSB_FLAGS_VALID_COORDS and back.flags & M.ADSB_FLAGS_VALID_CALLSIGN
    assert adsb_contact(person(geo=False)) is None                        # no home yet: no map position


@pytest.mark.parametrize("cls, ident, want", [("person", 7, b"PERSON7"), ("fire hydrant", 123, b"FIREH123"),
                                              ("car", 12345678, b"12345678")])
def test_callsigns_fit_eight_characters(cls, ident, want):
    o = TrackedObject(track_id=ident, class_name=cls)
    assert callsign(o) == want and len(callsign(o)) <= 8


def test_confirmed_objects_are_refreshed_once_a_second_and_dropped_when_gone():
    relay = ObjectsRelay(refresh_s=1.0)
    frame = TrackedObjectArray(header=Header(stamp_ns=1), objects=[person(7), person(8, confirmed=False)])
    assert [m.ICAO_address & 0xFFFF for m in relay.contacts(frame, 10.0)] == [7]
    assert relay.contacts(frame, 10.5) == []
    assert len(relay.contacts(frame, 11.0)) == 1
    relay.contacts(TrackedObjectArray(objects=[]), 11.2)                  # track 7 lost
    assert relay.sent_s == {}
