"""The .msg files an independent ROS 2 node (PyPI `zenoh-ros2-sdk`) reads, written from rosbags'
ROS 2 Jazzy store: this machine cannot reach the SDK's default source (it clones
ros2/common_interfaces from GitHub). The SDK parses and hashes them itself."""
from __future__ import annotations

from pathlib import Path

SEP = "=" * 80 + "\n"


def write_msg_files(folder: Path, ros_types: list[str]) -> None:
    """<folder>/<pkg>/msg/<Type>.msg for every type (and dependency) in `ros_types`."""
    from aeroperception.services.ros2bridge.rmw import make_typestore

    store = make_typestore()
    for typ in ros_types:
        blocks = store.generate_msgdef(typ, ros_version=2)[0].split(SEP)
        named = [(typ, blocks[0])] + [tuple(b.split("\n", 1)) for b in blocks[1:]]
        for name, body in named:
            name = name.removeprefix("MSG: ")
            pkg, _, short = name.partition("/")
            d = folder / pkg / "msg"
            d.mkdir(parents=True, exist_ok=True)
            (d / f"{short.rsplit('/', 1)[-1]}.msg").write_text(body)
