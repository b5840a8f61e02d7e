"""Contract of the objects service: keys in/out and parameters.

Each detection frame is placed in the world at the pose of its image's stamp (stereo disparity in
the box, else the box's ray to flat ground), tracked, and published with every live track.
"""
from aeroperception.schemas import (
    CameraInfo, Detection2DArray, HomePosition, Image, ObjectEvent, TrackedObjectArray, VehicleState,
)
from aeroperception.services.runtime import Param, Queries, Query, Topic, Topics

NAME = "objects"
INPUTS = Topics(
    Topic("perception/detections", Detection2DArray, note="the left image's stamp; newest wins"),
    Topic("sensors/camera/left/image", Image, note="the stereo pair, kept ~1 s by stamp"),
    Topic("sensors/camera/right/image", Image),
    Topic("sensors/camera/left/info", CameraInfo),
    Topic("sensors/camera/right/info", CameraInfo),
    Topic("state/vehicle", VehicleState, note="pose history, interpolated at the image's stamp"),
    Topic("fmu/out/home_position", HomePosition, note="latched: lat/lon/alt of tracks, and the flat ground's height"),
)
OUTPUTS = Topics(
    Topic("perception/objects", TrackedObjectArray, 10.0,
          note="at most: with each detection frame, every live track (the image's stamp)"),
    Topic("perception/objects/events", ObjectEvent, note="event: a track confirmed (new object), lost or reacquired"),
)
CALLS = Queries(
    Query("sensors/camera/left/info", None, CameraInfo, note="once at start (the latched camera model)"),
    Query("sensors/camera/right/info", None, CameraInfo),
)
# Typical sizes (length, width, height; m) of what the detector reports. The ground path aims at
# an object's mid-height; stereo sees its near face, the centre lies half a footprint behind it.
TYPICAL_SIZE_M = {
    "person": (0.45, 0.5, 1.75), "bicycle": (1.75, 0.6, 1.1), "car": (4.5, 1.85, 1.5), "motorcycle": (2.1, 0.8, 1.2),
    "bus": (12.0, 2.55, 3.2), "truck": (8.0, 2.5, 3.4), "dog": (0.9, 0.3, 0.6), "horse": (2.4, 0.7, 1.7),
    "cow": (2.4, 0.8, 1.5), "bench": (1.8, 0.6, 0.9), "chair": (0.5, 0.5, 0.9), "fire hydrant": (0.3, 0.3, 0.8),
    "stop sign": (0.1, 0.75, 2.5), "potted plant": (0.5, 0.5, 0.8),
}
DEFAULT_SIZE_M = (1.0, 1.0, 1.0)
PARAMS = [
    Param("stereo", True, description="range from the stereo pair's disparity in the box when it is there"),
    Param("stereo_max_range_m", 15.0, "m", 1.0, 100.0, description="search disparities down to this range"),
    Param("max_range_m", 60.0, "m", 5.0, 500.0, description="farther placements are dropped (counted)"),
    Param("ground_z_m", 0.0, "m", -1000.0, 10000.0,
          description="ENU height of the flat ground before the FC's home is known (then: home's)"),
    Param("pose_tolerance_s", 0.1, "s", 0.005, 1.0,
          description="a detection whose stamp has no vehicle pose this close is dropped (counted)"),
    Param("pixel_sigma_px", 2.0, "px", 0.1, 50.0, description="1 sigma of a box centre"),
    Param("disparity_sigma_px", 0.25, "px", 0.01, 5.0, description="1 sigma of a box's median disparity"),
    Param("height_sigma_m", 0.3, "m", 0.0, 5.0, description="1 sigma of an object's mid-height above the ground"),
    Param("position_sigma_m", 0.1, "m", 0.0, 10.0, description="1 sigma of the vehicle's position"),
    Param("pose_time_sigma_s", 0.02, "s", 0.0, 0.5,
          description="1 sigma of when the vehicle's pose (state/vehicle) was true against the image's stamp "
                      "(estimator lag, interpolation): the turn rate times it widens each placement like pixel noise. "
                      "Pitching into a leg (3.8 rad/s) the pose's attitude trailed the camera's by ~15 ms (2-3 deg) "
                      "and a whole frame's ground placements fell 1.5-5 m long at 12-28 m; 0: off"),
    Param("attitude_sigma_rad", 0.01, "rad", 0.0, 0.5, description="1 sigma of the camera's attitude"),
    Param("min_score", 0.1, "", 0.0, 1.0, description="detections below are ignored (ByteTrack's low threshold)"),
    Param("high_score", 0.5, "", 0.0, 1.0, description="only detections at or above start tracks; lower ones extend them"),
    Param("confirm_hits", 3, "", 1, 100, description="a track is confirmed (event) after this many detections"),
    Param("lost_timeout_s", 3.0, "s", 0.1, 600.0, description="a confirmed track unseen this long is lost (event)"),
    Param("forget_s", 600.0, "s", 0.0, 86400.0,
          description="a lost track is remembered this long: seen again within gate_distance_m it is reacquired (same id, event)"),
    Param("tentative_timeout_s", 1.0, "s", 0.05, 60.0,
          description="an unconfirmed track unseen this long is deleted (longer than the detection period)"),
    Param("birth_sigma_m", 2.0, "m", 0.05, 100.0,
          description="a detection placed less precisely than this (horizontal 1 sigma; far ones) only extends tracks, never starts one"),
    Param("birth_spacing_m", 2.5, "m", 0.0, 50.0,
          description="a detection this close (horizontally) to a known track of its class never starts a track: that object seen with a bias, not a second one (two objects of a class closer than this are one track)"),
    Param("partial_ratio", 1.25, "", 1.01, 10.0,
          description="a box this much shorter or taller (at its range) than the track's last boxes is a partial view: it keeps the track alive without moving it"),
    Param("partial_scale", 0.75, "", 0.0, 1.0,
          description="a box shorter than this fraction of what its class's typical size fills at its range is a partial view (occluded): it keeps a track alive without moving it and starts none"),
    Param("crowd_scale", 2.0, "", 1.0, 10.0,
          description="a box taller than this many times what its class's typical size fills at its range takes in more than the object (a neighbour): it keeps a track alive without moving it and starts none"),
    Param("confirm_scale", 0.92, "", 0.0, 10.0,
          description="a track is confirmed only when at least half of its whole boxes (since it started) are this tall or taller against what its class's typical size fills from there (box_scale): the detector boxes whole objects at 1.10-1.31x (each class's median), a low wall it takes for a truck at 0.71-0.96x; 0: any size"),
    Param("partial_sigma_scale", 1.0, "", 0.0, 10.0,
          description="a box shorter than the track's whole boxes (a fraction r of their median box_scale) may show part of the object: "
                      "its placement moves the track with 1 sigma this times (1 - r) times its class's typical length added horizontally "
                      "(the village's truck nearing end-on, boxed by its cab more and more: placed 0.8-1.3 m off at r 0.85-0.92, 2.2 m at 0.80); 0: off"),
    Param("coast_tau_s", 0.5, "s", 0.0, 60.0,
          description="an unseen track's velocity decays with this time constant (0: kept); a static object's spurious velocity must not carry it away"),
    Param("gate_distance_m", 3.0, "m", 0.1, 50.0, description="a detection farther than this from a track never joins it"),
    Param("accel_sigma_mps2", 0.2, "m/s^2", 0.0, 20.0, description="constant-velocity model's process noise"),
]
