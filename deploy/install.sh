#!/usr/bin/env bash
# Install AeroPerception on a fresh Debian/Ubuntu machine: the system libraries the wheels load
# at import time (apt, when root or with sudo), then the package itself in editable mode.
#   deploy/install.sh              -> extras sim,perception,tools: what the default profile starts
#                                     (tools/profiles.yaml sim `install:`; a unit test keeps them equal)
#   deploy/install.sh sim,perception,tools,test          (what .ci/run uses)
#   deploy/install.sh sim,tools,bench                    (+ dora-rs and Cyclone DDS for `aero bench pubsub --peers`)
#   deploy/install.sh --apt-only                         (system libraries only: deploy/Dockerfile's first layer)
# APT_PACKAGES below is the one list of system libraries, for machines and the image alike.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
APT_ONLY=0
if [ "${1:-}" = "--apt-only" ]; then APT_ONLY=1; shift; fi
EXTRAS=${1:-sim,perception,tools}
PY=${PYTHON:-python3}
stamp() { echo "[install] $*"; }

# ---- system libraries the Python wheels load at import time
#   open3d: libusb-1.0-0, libudev1, libgl1/libegl1 (GLVND), libx11-6, libgomp1
#   opencv (headless, and the GUI build MAVProxy pulls in): libgl1, libglib2.0-0
APT_PACKAGES=(libusb-1.0-0 libudev1 libgl1 libegl1 libx11-6 libgomp1 libglib2.0-0)
#   test: headless Chromium + chromedriver load the Rerun web viewer (tests/integration/test_viz.py);
#   Xvfb + Mesa's software Vulkan (lavapipe) run the native viewer (tests/integration/test_viz_native.py);
#   iproute2 (ip, tc) + nftables (nft) build the test hosts and impair their links (tests/netns.py)
case ",$EXTRAS," in *,test,*) APT_PACKAGES+=(chromium chromium-driver xvfb mesa-vulkan-drivers iproute2 nftables) ;; esac
if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" != 0 ]; then
        if command -v sudo >/dev/null 2>&1; then SUDO="sudo -n"; else SUDO="skip"; fi
    fi
    if [ "$SUDO" = skip ]; then
        stamp "not root and no sudo: skipping apt-get (needs: ${APT_PACKAGES[*]})"
    else
        stamp "apt-get install ${APT_PACKAGES[*]}"
        export DEBIAN_FRONTEND=noninteractive
        $SUDO apt-get update -qq
        $SUDO apt-get install -y -qq --no-install-recommends "${APT_PACKAGES[@]}" >/dev/null
    fi
else
    stamp "no apt-get: assuming ${APT_PACKAGES[*]} are present"
fi
[ "$APT_ONLY" = 1 ] && exit 0

# ---- Python packages (Debian's own python3 refuses pip without this; harmless elsewhere), at the
# versions CI tested: deploy/constraints.txt (refreshed by deploy/lock.sh). AERO_DEPS=newest installs
# today's newest releases instead, to find what they break on purpose (`AERO_DEPS=newest .ci/run`).
export PIP_BREAK_SYSTEM_PACKAGES=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
case ${AERO_DEPS:-locked} in
    locked) PINS=(-c deploy/constraints.txt) ;;
    newest) PINS=(--upgrade --upgrade-strategy eager) ;;
    *) echo "install.sh: AERO_DEPS must be locked or newest, not '${AERO_DEPS}'" >&2; exit 2 ;;
esac
stamp "pip install ${PINS[*]} -e .[$EXTRAS]"
"$PY" -m pip install -q "${PINS[@]}" -e ".[$EXTRAS]"
CHECK="import aeroperception.tools.cli, zenoh, msgspec, pymavlink"
case ",$EXTRAS," in *,sim,*) CHECK="$CHECK, open3d, cv2, numba" ;; esac
case ",$EXTRAS," in *,perception,*) CHECK="$CHECK, onnxruntime, gtsam" ;; esac
case ",$EXTRAS," in *,bench,*) CHECK="$CHECK, dora, cyclonedds" ;; esac
"$PY" -c "$CHECK; print('install: imports ok')"
# The versions that matter most to a bug report, in one line (all of them: pip freeze).
"$PY" - <<'VERSIONS'
from importlib.metadata import PackageNotFoundError, version
names = ("eclipse-zenoh", "msgspec", "numpy", "pymavlink", "opencv-python-headless", "open3d", "gtsam",
         "onnxruntime", "rerun-sdk", "mcap", "pytest")
found = []
for n in names:
    try:
        found.append(f"{n}=={version(n)}")
    except PackageNotFoundError:
        pass
print("[install] " + " ".join(found))
VERSIONS

