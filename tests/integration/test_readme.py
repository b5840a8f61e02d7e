"""The commands of the README and of every docs page, run: every command line of every ```bash
block in README.md and docs/**/*.md is listed in HOW below, and a line that is not is a test
failure (so is a HOW entry no page has any more), so an example cannot change (or rot) unseen.

- "stack": run against a real `aero up --except planner` stack (sim, fmu, mission, gcs,
  diagnostics on free ports, no sensor rendering) with `aero run planner --param kp=1.0` in the
  foreground beside it — the docs' own "run one service yourself" pattern — in page order, each
  line once. Commands that would run forever get a bound (`--duration`, `--timeout`); the rest run
  as written.
- "dry": `aero up` lines run with `--dry-run`: the arguments are validated and the command line
  of every service printed, nothing starts (they need a real FC, QGC, or the fixed ports).
- "skip": what cannot run here (installing with apt, the whole CI, an interactive MAVProxy),
  with the test that covers it instead, and a syntax or `--help` check where there is one.

Quick start and first examples: every command line of the README (the quick start and the tour)
and the first command line of every docs page must be "stack", "dry", or "skip" with a check argv
that is executed (`test_quick_start_and_first_examples_are_executed` enforces it), so the commands
a reader tries first are run or validated, not only listed.
"""
from __future__ import annotations

import re
import shlex
import subprocess
import time
from pathlib import Path

import pytest

from aerotest import aero, aero_argv, clean_env, free_port, free_udp_port, wait_for_message, wait_until

from aeroperception.schemas import VehicleState

REPO = Path(__file__).resolve().parents[2]

STACK, DRY, SKIP = "stack", "dry", "skip"
# README line -> (how, argv to run instead or extra flags, what stdout must contain)
HOW: dict[str, tuple] = {
    "deploy/install.sh && aero up": (SKIP, ["bash", "-n", "deploy/install.sh"],
                                     "installs apt packages and pip: checked for syntax; `aero up` as a dry run below"),
    ".ci/run": (SKIP, ["bash", "-n", ".ci/run"], "it is this test suite (plus the install): checked for syntax"),
    "AERO_DEPS=newest .ci/run": (SKIP, ["bash", "-n", ".ci/run"],
                                 "the suite on today's releases (install.sh's AERO_DEPS): checked for syntax"),
    "deploy/lock.sh": (SKIP, ["bash", "-n", "deploy/lock.sh"],
                       "re-resolves the pins and runs the whole CI: test_lock checks the lock it writes"),
    "aero run lidar_driver --param device_ip=192.168.1.201": (
        SKIP, ["aero", "run", "lidar_driver", "--help"],
        "needs a LiDAR on the network: test_lidar_driver_service replays a real VLP-16 capture into it over UDP"),
    "aero eval vio --live --duration 16": (SKIP, ["aero", "eval", "vio", "--help"],
                                           "needs a played recording: test_play scores the MH_01 clip live"),
    "aero play euroc ../shared/data/euroc/MH_01_clip": (
        SKIP, ["aero", "play", "euroc", "--help"], "test_play plays it into the vio service and scores it"),
    "aero play pcap vlp16.pcap --to 127.0.0.1 --port 2368": (
        SKIP, ["aero", "play", "pcap", "--help"], "test_play sends a real VLP-16 capture to a lidar_driver"),
    "aero run camera --param source=/dev/video0 --param calibration_path=camchain.yaml": (
        SKIP, ["aero", "run", "camera", "--help"],
        "needs a camera: test_camera_service runs it on EuRoC images with a Kalibr calibration"),
    "aero run camera --param source=/dev/video0 --param layout=side_by_side --param calibration_path=stereo.yml": (
        SKIP, ["aero", "run", "camera", "--help"], "test_camera_service splits a side-by-side video"),
    "aero run camera --param source=../shared/data/euroc/MH_01_clip/mav0/cam0/data": (
        SKIP, ["aero", "run", "camera", "--help"], "runs until stopped: test_camera_service plays the folder"),
    "aero up --profile vehicle --fcu-url /dev/ttyACM0,921600 --sensors-file sensors.yaml": (
        SKIP, ["aero", "up", "--help"], "needs a flight controller and the sensors: test_vehicle_sensors brings the "
                                        "profile up with a sensors file, test_up_sensors decodes them"),
    "aero up --profile vehicle --sensors-file sensors.yaml --dry-run": (
        SKIP, ["aero", "up", "--help"], "sensors.yaml is the page's example: test_up_sensors plans it"),
    "aero eval vio --euroc ../shared/data/euroc/MH_01_clip": (
        SKIP, ["aero", "eval", "vio", "--help"], "~15 s of VIO: test_vio_euroc_motion scores the MH_01 clip offline"),
    "aero bench vio --euroc ../shared/data/euroc/MH_01_clip -n 240": (
        SKIP, ["aero", "bench", "vio", "--help"], "a benchmark (figures, not a test): test_vio_euroc_motion runs the frames"),
    "aero doctor": (SKIP, ["aero", "doctor", "--help"],
                    "exits 1 on a busy default port: test_doctor_cli runs it on free ports and on a held one"),
    "aero doctor --profile px4 --px4 DIR": (SKIP, ["aero", "doctor", "--help"],
                                            "DIR is a placeholder: test_doctor checks PX4 dirs with and without bin/px4"),
    "aero mission fly examples/missions/survey_01.json": (
        STACK, ["aero", "mission", "load", "examples/missions/survey_01.json"],
        "loaded"),   # flying it takes minutes: test_flight flies missions (slow); here it is validated and loaded
    "aero mission fly examples/missions/survey_01.json --trajectory smooth": (
        STACK, ["aero", "mission", "load", "examples/missions/survey_01.json", "--trajectory", "smooth"],
        "loaded"),   # test_trajectory_flight flies it (slow)
    "aero plugin set trajectory_generator smooth": (
        STACK, ["aero", "plugin", "set", "trajectory_generator", "waypoint"], "trajectory_generator = waypoint"),
    "aero plugin list": (STACK, None, "controller"),
    "aero plugin set controller velocity": (
        STACK, ["aero", "plugin", "set", "controller", "feedforward"], "controller = feedforward"),
    "aero eval trajectory --live --until-landed --json traj.json": (
        SKIP, ["aero", "eval", "trajectory", "--help"], "needs a flight: test_trajectory_flight scores two by truth"),
    "aero node list": (STACK, None, "planner"),
    "aero topic list": (STACK, None, "state/vehicle"),
    "aero topic echo state/vehicle -n 1": (STACK, ["--timeout", "15"], "# state/vehicle [VehicleState@"),
    "aero topic hz fmu/in/trajectory_setpoint": (STACK, ["--duration", "3"], "fmu/in/trajectory_setpoint: rate"),
    "aero topic pub mission/command --type MissionCommand '{command: HOLD}'": (STACK, None, ""),
    "aero service call fmu/srv/set_mode '{mode: HOLD}' --type SetModeRequest": (STACK, None, "success: true"),
    "aero param list planner": (STACK, None, "max_velocity_mps"),
    "aero param set planner max_velocity_mps 3.0": (STACK, None, "max_velocity_mps = 3.0"),
    "aero mission command LAND": (STACK, None, None),
    "aero schema show VehicleState": (STACK, None, "VehicleState@"),
    "aero schema export --out schema/": (STACK, None, "JSON Schema files"),
    "aero snapshot --out shots/": (SKIP, ["aero", "snapshot", "--help"],
                                   "needs the rendered sensors (2 cores): test_sim_sensors_stack runs it"),
    "aero bench pubsub": (STACK, ["-n", "300", "--port", "{free_port}"], "median"),
    "aero up --except planner": (STACK, None, None),   # the `readme_stack` fixture itself
    "aero run planner --param kp=1.0": (STACK, None, None),   # started beside it by the fixture
    "aero up": (DRY, None, "sim "),
    "aero up --arg gcs:--gcs-ip=192.168.1.20": (DRY, None, "--gcs-ip=192.168.1.20"),
    "mavproxy.py --master=udpin:127.0.0.1:14550": (SKIP, None, "interactive ground station: test_gcs drives MAVProxy"),
    "aero up --arg gcs:--signing-key-file=/etc/aero/gcs.key": (DRY, None, "--signing-key-file=/etc/aero/gcs.key"),
    "aero fc params show gps-denied": (SKIP, ["aero", "fc", "params", "show", "gps-denied"], "needs no stack: run as written"),
    "aero fc params apply gps-denied --fcu-url /dev/ttyACM0,921600": (
        SKIP, ["aero", "fc", "params", "apply", "--help"],
        "needs a real FC: test_fc_params applies it to a PX4 stand-in, test_px4_gps_denied the SITL set to PX4"),
    "aero fc params apply gps-denied-sih --fcu-url udpout:127.0.0.1:18570": (
        SKIP, ["aero", "fc", "params", "show", "gps-denied-sih"],
        "needs PX4 SITL instance 0: test_px4_gps_denied applies it to its own instance"),
    "aero up --profile px4 --px4 ~/PX4-Autopilot/build/px4_sitl_default": (
        SKIP, ["aero", "up", "--help"], "needs a PX4 build: test_px4 flies the bundle through this profile"),
    "aero up --profile px4 --px4 DIR --px4-instance 1": (
        SKIP, ["aero", "up", "--help"], "test_px4 runs PX4 as a free instance >= 1; test_px4_sitl the checks"),
    "aero up --profile px4 --px4 DIR --dry-run": (
        SKIP, ["aero", "up", "--help"], "test_px4_sitl checks PX4's environment and command line"),
    "aero up --profile px4 --px4 DIR --scenario village": (
        SKIP, ["aero", "up", "--help"], "needs a PX4 build: test_px4_sensors runs this profile on the bundle, village"),
    "aero up --profile px4 --px4 DIR --scenario village --sensors lidar": (
        SKIP, ["aero", "up", "--help"], "test_px4_sitl: --sensors narrows the px4 profile as the sim profile"),
    "aero up --profile ardupilot --ardupilot ../shared/ardupilot/ardupilot-sitl-copter.tar.gz": (
        SKIP, ["aero", "up", "--help"], "needs ArduCopter SITL: test_ardupilot flies the bundle through this profile"),
    "AERO_ARDUPILOT_DIR=~/ardupilot aero up --profile ardupilot --ardupilot-instance 1": (
        SKIP, ["aero", "up", "--help"], "test_ardupilot runs it as a free instance >= 1; test_ardupilot_sitl the checks"),
    "pytest -m ardupilot tests/integration/test_ardupilot.py": (
        SKIP, None, "the test itself (marker ardupilot)"),
    "DIR/bin/px4-commander --instance 0 mode auto:loiter": (
        SKIP, None, "test_px4 switches its PX4 to HOLD this way mid-mission"),
    "aero up --profile vehicle": (DRY, None, "--param publish_imu=true"),
    "aero up --profile vehicle --fcu-url udpin:0.0.0.0:14540": (DRY, None, "--fcu-url udpin:0.0.0.0:14540"),
    "aero up --profile vehicle --fcu-url /dev/ttyACM0,921600": (DRY, None, "--fcu-url /dev/ttyACM0,921600"),
    "aero node list --connect tcp/VEHICLE_IP:7447": (STACK, None, "planner"),
    "aero run planner --connect tcp/VEHICLE_IP:7447": (STACK, None, None),   # the fixture's planner uses --connect
    "aero topic hz perception/costmap": (SKIP, ["aero", "topic", "hz", "--help"],
                                         "needs the LiDAR rendered (2 cores): test_lidar_service and test_obstacle_flight"),
    "aero param set lidar overhead_clearance_m 2.0": (SKIP, ["aero", "param", "set", "--help"],
                                                     "needs the lidar service: test_lidar_service runs it"),
    "aero eval lidar": (SKIP, ["aero", "eval", "lidar", "-n", "2", "--scenario", "open_field", "--kitti"],
                        "the full run renders 60 scans: checked on two"),
    "aero bench lidar": (SKIP, ["aero", "bench", "lidar", "-n", "1"], "a benchmark: checked with one scan"),
    "aero service call safety/srv/emergency_stop '{confirm: true, reason: \"operator: fly-away\"}' --type EmergencyStopRequest": (
        SKIP, ["aero", "service", "call", "--help"], "stops the motors: test_safety executes it on a sim stack"),
    "aero eval vio --euroc ../shared/data/euroc/V1_01_easy_start": (
        SKIP, ["aero", "eval", "vio", "--help"], "the EuRoC run is test_vio_euroc's (still start, preintegration)"),
    "aero bench vio": (SKIP, ["aero", "bench", "vio", "--help"], "a benchmark: renders 200 stereo frames"),
    "aero chaos --list": (SKIP, ["aero", "chaos", "--list"], "lists the rows"),
    "aero chaos --rows kill_planner,gcs_loss --json chaos.json": (
        SKIP, ["aero", "chaos", "--help"], "flies a mission per row: tests/faults runs the rows"),
    "aero chaos --profile px4 --px4 DIR --rows pilot_hold,failsafe_rtl": (
        SKIP, ["aero", "chaos", "--profile", "px4", "--help"],
        "needs a PX4 build: tests/faults/test_chaos_px4.py flies the rows on the bundle"),
    "aero topic echo perception/costmap -n 1": (SKIP, ["aero", "topic", "echo", "--help"],
                                                "needs the LiDAR rendered (2 cores): test_lidar_service reads the costmap"),
    "aero eval lidar --altitude 4 --altitude 1.5": (SKIP, ["aero", "eval", "lidar", "--help"],
                                                    "renders 60 scans per height: `aero eval lidar` is checked on two"),
    "aero up --arg detector:--param=model_path=/abs/path/best.onnx": (DRY, None, "--param=model_path=/abs/path/best.onnx"),
    "aero param set detector model_path /abs/path/yolov8n.onnx": (
        SKIP, ["aero", "param", "set", "--help"], "test_detector_service hot-swaps models through it"),
    "aero bench detector": (SKIP, ["aero", "bench", "detector", "--help"], "a benchmark: minutes of inference"),
    "aero up --profile viz": (DRY, None, "aeroperception.services.viz"),
    "aero viz --web 9090": (SKIP, ["aero", "viz", "--help"], "test_viz serves the web viewer and screenshots it"),
    "aero viz --viewer rerun+http://laptop:9876/proxy": (
        SKIP, ["aero", "viz", "--help"], "test_viz_service streams to a Rerun gRPC relay"),
    "aero viz --save flight.rrd": (SKIP, ["aero", "viz", "--help"], "test_viz reads a saved .rrd back"),
    "aero viz": (SKIP, ["aero", "viz", "--help"], "the native viewer needs a display"),
    "Xvfb :1 -extension Composite &": (SKIP, ["bash", "-c", "command -v Xvfb"], "test_viz_native runs it"),
    "DISPLAY=:1 WGPU_BACKEND=vulkan aero viz": (SKIP, ["aero", "viz", "--help"],
                                                "test_viz_native: aero viz on Xvfb + lavapipe, screenshot checked"),
    "aero record --images sensors/imu 'sensors/camera/*/info'": (
        SKIP, ["aero", "record", "--help"], "runs until Ctrl-C: test_recorder_perception records the VIO inputs"),
    "aero run vio --sim-time": (SKIP, ["aero", "run", "vio", "--help"], "test_recorder_perception runs it on the replay, test_play on the MH_01 clip"),
    "aero replay FILE.mcap --keys sensors/imu 'sensors/camera/*/image' 'sensors/camera/*/info'": (
        SKIP, ["aero", "replay", "--help"], "test_recorder_perception: replayed VIO matches the live one"),
    "aero service call vio/srv/reset '{pose: {position: {x: 10, y: -2, z: 3}}}' --type VioResetRequest": (
        SKIP, ["aero", "service", "call", "--help"],
        "needs a running vio: test_vio_service resets the real service to (10, -2, 3) and refuses bad poses"),
    "aero mission fly examples/missions/village_tour.json": (
        SKIP, ["aero", "mission", "fly", "--help"], "test_detector_eval_live flies it (opt-in extended)"),
    "aero eval detector --live --until-landed --duration 600": (
        SKIP, ["aero", "eval", "detector", "--help"], "test_detector_eval_live evaluates the flight (opt-in extended)"),
    "aero record -o recordings": (SKIP, ["aero", "record", "--help"], "runs until Ctrl-C: test_recorder records a flight"),
    "aero record --preset all --images -o recordings": (SKIP, ["aero", "record", "--help"], "test_recorder"),
    "aero mcap info recordings/FILE.mcap": (SKIP, ["aero", "mcap", "info", "--help"], "FILE is a placeholder: test_recorder"),
    "aero replay recordings/FILE.mcap --rate 2 --keys state/vehicle mission/active_goal": (
        SKIP, ["aero", "replay", "--help"], "test_recorder replays a flight byte-equal"),
    "aero mcap recover recordings/FILE.mcap": (SKIP, ["aero", "mcap", "recover", "--help"],
                                               "test_recorder recovers a file cut by kill -9"),
    "aero mcap export recordings/FILE.mcap --foxglove": (SKIP, ["aero", "mcap", "export", "--help"],
                                                         "test_recorder validates the export"),
    "aero certs --out certs --host VEHICLE_IP": (SKIP, ["aero", "certs", "--help"], "test_certs / test_security"),
    "AERO_ROUTER_CONFIG=certs/router.json5 AERO_ZENOH_CONFIG=certs/vehicle.json5 aero up --listen tls/0.0.0.0:7447": (
        SKIP, None, "test_security starts exactly this across network namespaces"),
    "AERO_ZENOH_CONFIG=certs/ground.json5 aero node list --connect tls/VEHICLE_IP:7447": (SKIP, None, "test_security"),
    "zenoh --mode client --connect tcp/127.0.0.1:7447 subscribe -k 'state/**' --decoder aero": (
        SKIP, None, "test_zenoh_cli runs it against a real router"),
    "zenoh --mode client --connect tcp/127.0.0.1:7447 put -k mission/command --encoder aero -v '{command: HOLD}'": (
        SKIP, None, "test_zenoh_cli runs it against a real router"),
    "aero run ros2bridge --param topics=state/vehicle,sensors/imu,perception/detections": (
        SKIP, ["aero", "run", "ros2bridge", "--help"], "test_ros2bridge runs the bridge against zenoh-ros2-sdk"),
    "ros2 topic echo /aero/odom": (SKIP, None, "needs ROS 2: test_ros2bridge plays the ROS node with zenoh-ros2-sdk"),
    "aero run ros2bridge --param inputs=/ouster/points=sensors/lidar/points,/imu/data=sensors/imu": (
        SKIP, ["aero", "run", "ros2bridge", "--help"],
        "needs a ROS 2 driver: test_ros2bridge_sensors publishes real KITTI scans and EuRoC IMU rows from zenoh-ros2-sdk"),
    "aero run ros2bridge --param inputs=/camera/color/image_raw=sensors/camera/left/image,"
    "/camera/color/camera_info=sensors/camera/left/info --param left_mount_pitch_deg=30": (
        SKIP, ["aero", "run", "ros2bridge", "--help"],
        "needs a ROS 2 camera: test_ros2bridge_sensors publishes EuRoC frames and CameraInfo from zenoh-ros2-sdk"),
    "ros2 run velodyne_driver velodyne_driver_node": (SKIP, None, "needs ROS 2 and a Velodyne: test_ros2bridge_sensors "
                                                                  "plays a driver's PointCloud2 with zenoh-ros2-sdk"),
    "aero up --gps-denied --scenario village --sensors camera": (DRY, None, "SIM_GPS_DENIED"),
    "aero mission fly examples/missions/village_survey_gps_denied.json": (
        SKIP, ["aero", "mission", "fly", "--help"],
        "flies minutes on VIO alone: test_gps_denied_flight (opt-in vio_e2e)"),
    "aero eval vio --live --until-landed --duration 600 --out vio_eval": (
        SKIP, ["aero", "eval", "vio", "--help"], "test_gps_denied_flight evaluates the live flight"),
    "aero param set sim SIM_CAM_BLACKOUT 3": (SKIP, ["aero", "param", "set", "--help"],
                                              "test_gps_denied_flight blacks out the cameras 3 s and 15 s"),
    "aero eval detector": (SKIP, ["aero", "eval", "detector", "--help"],
                           "test_detector_model checks the bundled model's held-out mAP on 16 frames"),
    "aero eval detector --live --detections": (SKIP, ["aero", "eval", "detector", "--help"],
                                               "test_detector_eval_live runs both live modes"),
    "aero up --profile sim --only sim,fmu,planner,safety --listen tcp/0.0.0.0:7447": (DRY, None, "router on tcp/0.0.0.0:7447"),
    "aero up --only mission,gcs --connect tcp/VEHICLE_IP:7447": (
        SKIP, ["aero", "up", "--help"], "test_multihost runs exactly this split across network namespaces"),
    "docker compose -f deploy/compose.yaml --profile sim up -d --build": (
        SKIP, None, "test_compose brings the sim profile up, flies survey_01, kills a container"),
    "docker compose -f deploy/compose.yaml ps": (SKIP, None, "test_compose waits for every service healthy"),
    "docker compose -f deploy/compose.yaml --profile sim down": (SKIP, None, "test_compose: nothing left running"),
    "deploy/docker-local.sh": (SKIP, ["bash", "-n", "deploy/docker-local.sh"], "installs the engine as root: syntax checked"),
    "BASE_IMAGE=aero-base:bookworm docker compose -f deploy/compose.yaml --profile sim up -d --build": (
        SKIP, None, "what test_compose runs"),
    # docs/simulate.md
    "aero up --scenario village --sensors camera": (DRY, None, "--scenario village --sensors camera"),
    "aero up --speed 4 --sensors none": (DRY, None, "--speed 4.0 --sensors none"),
    # docs/perception.md
    "aero topic echo perception/objects/events": (
        SKIP, ["aero", "topic", "echo", "--help"], "needs objects on rendered cameras: test_objects_stack reads the events"),
    "aero param set objects confirm_hits 5": (
        SKIP, ["aero", "param", "set", "--help"], "needs the objects service: test_objects_replay runs it with --param"),
    "aero eval objects --live --scenario village --until-landed --duration 480": (
        SKIP, ["aero", "eval", "objects", "--help"], "test_objects_search_flight scores this flight (opt-in extended)"),
    "aero mission fly examples/missions/village_search.json": (
        STACK, ["aero", "mission", "load", "examples/missions/village_search.json"],
        "loaded"),   # flown by test_objects_search_flight (extended): here validated and loaded
    # docs/benchmarks.md
    "aero bench stack": (SKIP, ["aero", "bench", "stack", "--help"],
                         "starts a whole stack for 30 s: test_bench_stack_logic pins its verdict"),
    "aero bench flight --sensors all": (SKIP, ["aero", "bench", "flight", "--help"], "a benchmark: needs the sim profile up"),
    "aero bench pubsub --peers": (SKIP, ["aero", "bench", "pubsub", "--help"],
                                  "dora-rs and Cyclone DDS come with the bench extra; `aero bench pubsub` runs on the stack"),
    "aero bench sim": (SKIP, ["aero", "bench", "sim", "--help"], "a benchmark: renders frames for minutes"),
    "aero bench objects": (SKIP, ["aero", "bench", "objects", "--help"], "a benchmark: test_objects_* time the pipeline"),
    "aero bench record": (SKIP, ["aero", "bench", "record", "--help"], "a benchmark: records images for seconds"),
    "aero bench soak --minutes 30": (SKIP, ["aero", "bench", "soak", "--help"], "flies missions for 30 minutes"),
    # docs/testing.md
    "python -m pytest -q tests/unit": (SKIP, None, "this suite's unit half"),
    "python -m pytest -m chaos_full tests/faults": (SKIP, None, "the opt-in fault rows of this suite"),
}


def doc_pages() -> list[Path]:
    """README.md, then every page of the docs site, in a stable order."""
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def page_commands(page: Path) -> list[str]:
    """Every command line of a page's ```bash blocks, trailing comments removed, in order."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", page.read_text(), re.S):
        for line in block.splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                out.append(re.sub(r"\s+#(\s.*)?$", "", line))
    return out


def readme_commands() -> list[str]:
    """Every command line of the README and the docs pages, in page order, each once."""
    return list(dict.fromkeys(c for page in doc_pages() for c in page_commands(page)))


def test_every_readme_command_is_run_or_explained():
    cmds = readme_commands()
    missing = [c for c in cmds if c not in HOW]
    assert not missing, f"README / docs commands this test does not know (add them to HOW): {missing}"
    stale = [c for c in HOW if c not in cmds]
    assert not stale, f"HOW lists commands no README or docs page has any more: {stale}"


def _executed(line: str) -> bool:
    how, argv = HOW[line][0], HOW[line][1]
    return how in (STACK, DRY) or (how == SKIP and bool(argv))


def test_quick_start_and_first_examples_are_executed():
    """The README's every command and each docs page's first command are run, dry-run, or checked."""
    firsts = {"README.md": page_commands(REPO / "README.md")}
    for page in doc_pages()[1:]:
        cmds = page_commands(page)
        if cmds:
            firsts[str(page.relative_to(REPO))] = cmds[:1]
    assert len(firsts) > 10, firsts
    unchecked = [f"{page}: {c}" for page, cmds in firsts.items() for c in cmds if c in HOW and not _executed(c)]
    assert not unchecked, f"quick-start / first-example lines that nothing runs: {unchecked}"


def test_readme_links_the_architecture_doc():
    text = (REPO / "README.md").read_text()
    assert "docs/ARCHITECTURE.md" in text and (REPO / "docs/ARCHITECTURE.md").is_file()
    assert "ARCHITECTURE §" not in text


def test_readme_links_every_task_page():
    text = (REPO / "README.md").read_text()
    pages = sorted(p.name for p in (REPO / "docs").glob("*.md"))
    unlinked = [p for p in pages if f"(docs/{p}" not in text]
    assert not unlinked, f"docs pages the README does not link: {unlinked}"
    assert "(docs/results/index.md)" in text


def _argv(line: str) -> list[str]:
    argv = shlex.split(line)
    return aero_argv() + argv[1:] if argv[0] == "aero" else argv


@pytest.mark.timeout(60)
@pytest.mark.parametrize("line", [c for c, h in HOW.items() if h[0] == DRY])
def test_readme_up_lines_validate_as_dry_runs(line):
    _how, _argv_over, expected = HOW[line]
    r = subprocess.run(_argv(line) + ["--dry-run"], capture_output=True, text=True, timeout=30,
                       env=clean_env(), cwd=REPO, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr
    assert "would start" in r.stdout and expected in r.stdout, r.stdout
    started = {ln.split()[0] for ln in r.stdout.splitlines()[1:]}
    assert ("planner" in started) == ("--except planner" not in line)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("line", [c for c, h in HOW.items() if h[0] == SKIP and h[1]])
def test_readme_skipped_lines_still_checked(line):
    _how, argv, _why = HOW[line]
    argv = aero_argv() + argv[1:] if argv[0] == "aero" else argv
    r = subprocess.run(argv, capture_output=True, text=True, timeout=30, cwd=REPO, env=clean_env(),
                       stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="module")
def readme_stack(stack_module):
    """`aero up --except planner` (free ports, no sensor rendering) and, beside it,
    `aero run planner --param kp=1.0 --connect <router>` in the foreground."""
    fcu, sim_bind, gcs_local, gcs_remote = (free_udp_port() for _ in range(4))
    st = stack_module(["sim", "fmu", "mission", "gcs", "diagnostics"], extra_args=[
        "--fcu-url", f"udpin:127.0.0.1:{fcu}", "--arg", f"sim:--target=127.0.0.1:{fcu}",
        "--arg", f"sim:--bind=127.0.0.1:{sim_bind}", "--sensors", "none",
        "--arg", f"gcs:--local-port={gcs_local}", "--arg", f"gcs:--remote-port={gcs_remote}",
        "--arg", "gcs:--bind-ip=127.0.0.1"], timeout_s=40)
    planner = subprocess.Popen(aero_argv() + ["run", "planner", "--param", "kp=1.0", "--connect", st.endpoint],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=clean_env(),
                               stdin=subprocess.DEVNULL)
    try:
        wait_until(lambda: st.alive("planner"), 15, "the foreground planner's liveliness token")
        wait_for_message(st.session, "state/vehicle", VehicleState, lambda m: m.connected, timeout_s=20)
        yield st
    finally:
        planner.send_signal(2)
        try:
            code = planner.wait(5)
        except subprocess.TimeoutExpired:
            planner.kill()
            planner.wait(5)
            code = None
        err = planner.stderr.read().decode(errors="replace")
        planner.stderr.close()
        assert code == 0, f"aero run planner did not stop cleanly on Ctrl-C: {code}\n{err[-2000:]}"


@pytest.mark.timeout(240)
def test_readme_commands_against_a_running_stack(readme_stack, tmp_path):
    st = readme_stack
    assert st.aero("param", "get", "planner", "kp").stdout.strip() == "1.0"  # `aero run planner --param kp=1.0`
    (tmp_path / "examples").symlink_to(REPO / "examples")  # the pages' paths are relative to the checkout
    failures = []
    for line in readme_commands():
        how, extra, expected = HOW[line]
        if how != STACK or expected is None:
            continue
        if extra and extra[0] == "aero":
            argv = extra
        else:
            argv = shlex.split(line.replace("tcp/VEHICLE_IP:7447", st.endpoint))
            argv += [a.replace("{free_port}", str(free_port())) for a in (extra or [])]
        t0 = time.monotonic()
        r = aero(*argv[1:], endpoint=st.endpoint, timeout_s=60, cwd=tmp_path)
        took = time.monotonic() - t0
        if r.returncode != 0 or expected not in r.stdout or "Traceback" in r.stderr or "warning" in r.stderr:
            failures.append(f"{line!r} -> exit {r.returncode} in {took:.1f} s\nstdout: {r.stdout[-800:]}\n"
                            f"stderr: {r.stderr[-800:]}")
    assert not failures, "\n\n".join(failures)
    assert len(list((tmp_path / "schema").glob("*.json"))) > 20   # `aero schema export --out schema/`


@pytest.mark.timeout(60)
def test_readme_mission_command_land_is_answered(readme_stack):
    """`aero mission command LAND` on a vehicle on the ground: the mission service answers
    (accepted, or refused with its reason in one line), never silence or a traceback."""
    r = readme_stack.aero("mission", "command", "LAND")
    assert "Traceback" not in r.stderr
    if r.returncode != 0:
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("aero:"), r.stderr
    else:
        assert r.stdout.strip() or r.stderr.strip()
