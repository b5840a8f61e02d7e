"""The VIO can start where every bundled scenario puts the vehicle: on the ground, the forward
camera (3 cm above the ground, which it sees at grazing angles) must see enough stereo features
for the KLT front end to initialise (FrontEndConfig.good_inliers) with a margin. open_field had 28
of 40 before its launch site (a barn and a hangar) was added: the first `aero up` never left INIT."""
import pytest

from aeroperception.services.sim.main import camera_info_msg
from aeroperception.services.sim.sensors.camera import StereoCamera
from aeroperception.services.sim.sensors.synthetic import hover_truth
from aeroperception.services.sim.world.scenario import available_scenarios, load_scenario
from aeroperception.services.sim.world.scene import get_scene
from aeroperception.services.vio.calibration import CameraCalibration
from aeroperception.services.vio.frontend import FrontEnd, FrontEndConfig


@pytest.mark.parametrize("name", available_scenarios())
def test_the_vio_sees_enough_to_start_on_the_ground(name):
    scn = load_scenario(name)
    stereo = StereoCamera(get_scene(scn), scn.sensors.camera)
    position, yaw = scn.start_pose()
    left, right = stereo.render(hover_truth(position, yaw))
    calib = CameraCalibration.from_camera_infos(*(camera_info_msg(i, 0) for i in stereo.infos()))
    fe = FrontEnd(calib)
    fe.process(0, left, right)
    assert len(fe.kf_px) >= 1.5 * FrontEndConfig.good_inliers, f"{name}: {len(fe.kf_px)} stereo features at start"
