"""`aero viz` with no flags spawns Rerun's native viewer: a smoke test on a virtual display.

Xvfb (Debian's xvfb) is the display and Mesa's software Vulkan (lavapipe, Debian's
mesa-vulkan-drivers) the GPU; deploy/install.sh installs both with the test extra. Xvfb runs
without its Composite extension: with it the viewer asks for a transparent (32-bit ARGB) window,
which nothing composites under Xvfb, and the window stays black. (Mesa's OpenGL llvmpipe is not
enough either: the viewer exits with "Adapter does not support drawing to texture format
R32Float".)

The test publishes a vehicle and a truth track on a real Zenoh router, runs `aero viz` against it,
and checks a screenshot of the display (path printed) is the viewer drawing both tracks. Skipped
where the packages are missing, except in CI.
"""
from __future__ import annotations

import glob
import math
import os
import select
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from aerotest import aero_argv, clean_env, free_port, interrupt, wait_until
from aeroperception.schemas import Header, Vector3, VehicleState
from aeroperception.services.viz import adapters as A

pytestmark = pytest.mark.timeout(120)

LAVAPIPE = "/usr/share/vulkan/icd.d/lvp_icd.*.json"
# rerun-sdk's `rerun` script sits next to this interpreter (also when its bin is not on PATH).
PATH = os.pathsep.join([os.path.dirname(sys.executable), os.environ.get("PATH", "")])


def missing() -> list[str]:
    out = []
    if shutil.which("Xvfb") is None:
        out.append("xvfb (Xvfb)")
    if not glob.glob(LAVAPIPE):
        out.append("mesa-vulkan-drivers (lavapipe)")
    if shutil.which("rerun", path=PATH) is None:
        out.append("rerun-sdk's `rerun` viewer")
    return out


def start_xvfb(log) -> tuple[subprocess.Popen, str, int]:
    """Xvfb on the first free display number (it writes the number to -displayfd; the pipe stays
    open while it runs, as it writes again on a server reset). -noreset: the last client leaving
    does not reset it."""
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-noreset", "-screen", "0", "1280x800x24",
                             "-nolisten", "tcp", "-extension", "Composite"], pass_fds=(w,), stdout=log,
                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    os.close(w)
    ready, _, _ = select.select([r], [], [], 15.0)
    number = os.read(r, 32).decode().strip() if ready else ""
    if not number:
        interrupt(proc)
        os.close(r)
        raise AssertionError("Xvfb did not report a display within 15 s")
    return proc, f":{number}", r


def descendants(pid: int) -> list[int]:
    """Every process below pid (the viewer rr.spawn started), read from /proc."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for task in glob.glob(f"/proc/{p}/task/*/children"):
            try:
                kids = [int(k) for k in open(task).read().split()]
            except OSError:
                continue
            out += kids
            todo += kids
    return out


def publish_tracks(make_node, stop_evt: threading.Event) -> None:
    """A vehicle flying a 6 m circle at 3 m, and its truth 0.5 m beside it, at 50 Hz."""
    node = make_node("fake_fmu")
    est, truth = node.publisher("state/vehicle", VehicleState), node.publisher("sim/truth/state", VehicleState)
    k = 0
    while not stop_evt.is_set() and k < 50 * 60:
        a = 0.03 * k
        for pub, r in ((est, 6.0), (truth, 6.5)):
            pub.publish(VehicleState(header=Header(stamp_ns=time.time_ns(), frame_id="map"), connected=True,
                                     position_m=Vector3(x=r * math.cos(a), y=r * math.sin(a), z=3.0)))
        k += 1
        time.sleep(0.02)


def colour_px(rgb: np.ndarray, colour: tuple[int, int, int]) -> int:
    return int((np.abs(rgb.reshape(-1, 3).astype(int) - np.array(colour)).max(axis=1) < 40).sum())


def test_native_viewer_draws_the_live_stream_on_a_virtual_display(zenoh_router, make_node, tmp_path):
    lacking = missing()
    if lacking:
        msg = f"not installed: {', '.join(lacking)} (deploy/install.sh installs them with the test extra)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    from PIL import ImageGrab

    xlog = open(tmp_path / "xvfb.log", "wb")
    xvfb, display, display_fd = start_xvfb(xlog)
    stop_evt = threading.Event()
    feeder = threading.Thread(target=publish_tracks, args=(make_node, stop_evt), daemon=True)
    env = dict(clean_env(zenoh_router), PATH=PATH, DISPLAY=display, WGPU_BACKEND="vulkan",
               VK_ICD_FILENAMES=glob.glob(LAVAPIPE)[0])
    vlog = open(tmp_path / "viz.log", "wb")
    viz = subprocess.Popen(aero_argv() + ["viz", "--param", f"grpc_port={free_port()}"], env=env, stdout=vlog,
                           stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    viewer: list[int] = []
    shot = tmp_path / "native_viewer.png"
    verdict: dict = {}
    try:
        feeder.start()

        def drawn() -> bool:
            assert viz.poll() is None, (tmp_path / "viz.log").read_text()[-3000:]
            viewer[:] = sorted(set(viewer) | set(descendants(viz.pid)))
            img = ImageGrab.grab(xdisplay=display)
            img.save(shot)
            rgb = np.asarray(img.convert("RGB"))
            colours = len(np.unique(rgb.reshape(-1, 3) // 8, axis=0))
            verdict.update(colours=colours, vehicle_px=colour_px(rgb, A.VEHICLE_COLOR),
                           truth_px=colour_px(rgb, A.TRUTH_COLOR))
            return colours > 50 and verdict["vehicle_px"] > 30 and verdict["truth_px"] > 30

        try:
            wait_until(drawn, 60, "the native viewer to draw both tracks", interval_s=2.0)
        finally:
            print(f"native viewer screenshot: {shot} ({verdict})")
    finally:
        stop_evt.set()
        feeder.join(5)
        code = interrupt(viz)
        for pid in viewer:               # the spawned viewer outlives viz: stop it by its pid
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        interrupt(xvfb)
        os.close(display_fd)
    assert code == 0, (tmp_path / "viz.log").read_text()[-3000:]
