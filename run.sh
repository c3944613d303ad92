#!/usr/bin/env bash
# Set up the project's environment in .venv (pinned versions) and run the demonstration or the tests.
#   ./run.sh demo [ARGS...]        the demonstration on the embedded simulator
#   ./run.sh test [PYTEST ARGS...] lint (ruff) and the test suite (pytest)
set -euo pipefail

ROOT="$(cd "$(dirname "$0")" && pwd)"
VENV="$ROOT/.venv"
PY="$VENV/bin/python"
STAMP="$VENV/.sma_stage-setup"
PIP_VERSION="26.3"
SETUP_FILES=(requirements.txt requirements-dev.txt setup.py setup.cfg package.xml)

say() { echo "run.sh: $*" >&2; }

usage() {
    echo "usage: ./run.sh demo [ARGS...] | ./run.sh test [PYTEST ARGS...]" >&2
    exit 2
}

is_python311() { "$1" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; }

find_python311() {
    local candidate
    for candidate in python3.11 python3; do
        if command -v "$candidate" >/dev/null && is_python311 "$candidate"; then
            echo "$candidate"
            return
        fi
    done
    say "Python 3.11 is required (as python3.11, or as python3 if that is 3.11)"
    exit 1
}

# What the installed environment depends on: the lock files, the package metadata, pip and where the repo is.
setup_fingerprint() {
    (cd "$ROOT" && cat "${SETUP_FILES[@]}" && echo "pip==$PIP_VERSION $ROOT") | sha256sum | cut -d' ' -f1
}

ensure_venv() {
    if [ ! -x "$PY" ] || ! is_python311 "$PY"; then
        local python
        python="$(find_python311)"
        say "creating .venv with $python"
        rm -rf "$VENV"
        "$python" -m venv "$VENV"
    fi

    local fingerprint
    fingerprint="$(setup_fingerprint)"
    if [ "$(cat "$STAMP" 2>/dev/null)" = "$fingerprint" ]; then
        return
    fi
    say "installing the pinned requirements and sma_stage into .venv (the first time takes a few minutes)"
    rm -f "$STAMP"
    "$PY" -m pip install -qq "pip==$PIP_VERSION"
    "$PY" -m pip install -qq -r "$ROOT/requirements-dev.txt"
    # Editable (PEP 660): console scripts land in .venv/bin, the code is read from the working tree.
    "$PY" -m pip install -qq --no-deps --no-build-isolation --editable "$ROOT"
    echo "$fingerprint" >"$STAMP"
}

# Keep ROS 2 traffic on this machine unless the caller chose otherwise.
export_ros_defaults() {
    export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
    export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
}

run_demo() {
    if ! "$PY" -c 'import importlib.util, sys; sys.exit(importlib.util.find_spec("sma_stage.demo") is None)'; then
        say "the demonstration module sma_stage.demo does not exist yet"
        exit 1
    fi
    exec "$PY" -m sma_stage.demo "$@"
}

run_tests() {
    "$PY" -m ruff check .
    local status=0
    # Two workers (the machines have two cores); a test file stays on one worker, so its cached fits are shared.
    "$PY" -m pytest -p no:cacheprovider -n 2 --dist loadfile --durations=20 "$@" || status=$?
    if [ "$status" -eq 5 ]; then
        say "pytest collected no tests: counted as a failure"
        exit 1
    fi
    exit "$status"
}

[ $# -ge 1 ] || usage
command="$1"
shift
cd "$ROOT"
case "$command" in
    demo) ensure_venv; export_ros_defaults; run_demo "$@" ;;
    test) ensure_venv; export_ros_defaults; run_tests "$@" ;;
    *) usage ;;
esac
