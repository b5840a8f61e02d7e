#!/usr/bin/env bash
# Refresh deploy/constraints.txt, the exact versions the suite was run with, and run the suite on them.
#   deploy/lock.sh            re-resolve every pin to today's newest release within pyproject.toml's ranges,
#                             then run .ci/run in a fresh venv on the new pins (commit both only if it passes)
#   deploy/lock.sh --no-test  re-resolve only (e.g. after adding a dependency: `--keep` pins what is pinned)
#   deploy/lock.sh --keep     resolve what pyproject.toml added or removed, keeping every other pin
# Installs read the file as pip constraints (deploy/install.sh, .ci/run, deploy/Dockerfile); AERO_DEPS=newest
# makes them ignore it, to find what today's releases break before a user does.
# The resolver is uv (a pinned copy in a throwaway venv: it is needed only here, never to install).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY=${PYTHON:-python3}
# The extras .ci/run installs (tests/unit/test_lock.py keeps the two lists equal).
LOCK_EXTRAS=(sim perception tools test)
UPGRADE=(--upgrade) TEST=1
for a in "$@"; do
    case $a in
        --no-test) TEST=0 ;;
        --keep) UPGRADE=() ;;
        *) echo "lock.sh: unknown option $a (see the header of deploy/lock.sh)" >&2; exit 2 ;;
    esac
done
tool=$(mktemp -d)
trap 'rm -rf "$tool"' EXIT
"$PY" -m venv "$tool"
"$tool/bin/python" -m pip install -q "uv==0.13.10"
extras=()
for e in "${LOCK_EXTRAS[@]}"; do extras+=(--extra "$e"); done
# --universal: one file for every Python >= 3.11 and platform (a marker picks the row); CI tests the
# rows of its own Python.
"$tool/bin/uv" pip compile pyproject.toml "${extras[@]}" "${UPGRADE[@]}" --universal --python-version 3.11 \
    --custom-compile-command "deploy/lock.sh" -o deploy/constraints.txt
[ "$TEST" = 1 ] || exit 0
venv=$(mktemp -d)
"$PY" -m venv "$venv"
PYTHON="$venv/bin/python" .ci/run
