import sys

try:
    from .main import main
except ModuleNotFoundError as e:
    if (e.name or "").split(".")[0] != "rosbags":
        raise
    # The bridge is optional (`aero up --profile ros2`): say what to install, in one line.
    print("ros2bridge: needs the optional extra 'ros2' (rosbags): pip install 'aeroperception[ros2]'",
          file=sys.stderr)
    sys.exit(2)

sys.exit(main())
