"""All sensors of a scenario's rig, built once and sharing one scene: what the sim service holds."""
from __future__ import annotations

from dataclasses import dataclass

from ..world.scenario import Scenario
from ..world.scene import Scene, get_scene
from .camera import Camera, StereoCamera, make_down_camera
from .imu import ImuModel
from .lidar import Lidar


@dataclass
class SimSensors:
    scene: Scene
    stereo: StereoCamera | None     # None when sensors.camera.enabled is false
    down: Camera | None             # None unless sensors.down_camera.enabled
    imu: ImuModel
    lidar: Lidar | None             # None when sensors.lidar.enabled is false

    def cameras(self) -> dict[str, Camera]:
        """The cameras built, by the name their keys carry (sensors/camera/<name>/image: contract.CAMERAS)."""
        cams = {"left": self.stereo.left, "right": self.stereo.right} if self.stereo is not None else {}
        cams["down"] = self.down
        return {name: cam for name, cam in cams.items() if cam is not None}


def build_sensors(scenario: Scenario) -> SimSensors:
    """Noise streams are seeded from scenario.seed, so a scenario replays identically."""
    rig = scenario.sensors
    scene = get_scene(scenario)
    return SimSensors(
        scene=scene,
        stereo=StereoCamera(scene, rig.camera) if rig.camera.enabled else None,
        down=make_down_camera(scene, rig.down_camera) if rig.down_camera.enabled else None,
        imu=ImuModel(rig.imu, seed=scenario.seed),
        lidar=Lidar(scene, rig.lidar, seed=scenario.seed) if rig.lidar.enabled else None,
    )
