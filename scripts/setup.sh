#!/usr/bin/env bash
# One place for every install step PreSim needs.
#   scripts/setup.sh              system libraries (apt, when root) + .venv with presim[all,test]
#   scripts/setup.sh --test-system  also ROS 1 (Debian packages) and chromium for the ROS / browser tests
# Idempotent: re-running only installs what is missing or changed.
set -euo pipefail
cd "$(dirname "$0")/.."

want_test_system=0
for arg in "$@"; do
  case "$arg" in
    --test-system) want_test_system=1 ;;
    *) echo "setup.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done

# --- system packages (Debian/Ubuntu, only when we can install them) -------------------------
apt_install() {
  local missing=()
  for p in "$@"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  [ ${#missing[@]} -eq 0 ] && return 0
  if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
    echo "setup.sh: please install these system packages: ${missing[*]}" >&2
    return 0
  fi
  echo "setup.sh: apt-get install ${missing[*]}"
  if ! DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/tmp/presim-apt.log 2>&1; then
    apt-get update -qq >/dev/null 2>&1 || true
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/tmp/presim-apt.log 2>&1 \
      || { echo "setup.sh: apt-get failed, see /tmp/presim-apt.log" >&2; tail -20 /tmp/presim-apt.log >&2; exit 1; }
  fi
}

if command -v dpkg >/dev/null; then
  # open3d-cpu links libusb and libgomp; the tf2_msgs build (presim ros2) needs cmake and a compiler.
  apt_install libusb-1.0-0 libgomp1 cmake g++
  if [ "$want_test_system" = 1 ]; then
    apt_install ros-core python3-rospy python3-std-msgs python3-sensor-msgs python3-geometry-msgs \
      python3-nav-msgs python3-tf2-msgs python3-std-srvs python3-rosgraph-msgs python3-diagnostic-msgs \
      chromium chromium-driver
  fi
fi

# --- Python environment ---------------------------------------------------------------------
PY=""
for c in python3.11 /usr/bin/python3.11 python3; do
  if command -v "$c" >/dev/null && "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then PY="$c"; break; fi
done
[ -n "$PY" ] || { echo "setup.sh: PreSim needs Python 3.11" >&2; exit 1; }

stamp=".venv/.presim-installed"
hash=$(cat pyproject.toml presim/outputs/ros2/tf2_build.py | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$hash" ]; then
  exit 0
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
# torch first and pinned: the CPU wheel on this disk; an unpinned torch would pull a multi-GB build.
.venv/bin/pip install -q --disable-pip-version-check "torch==2.13.0"
.venv/bin/pip install -q --disable-pip-version-check -e ".[all,test]"
# tf2_msgs is not on the index: generate it into the venv (idempotent; ~15-30 s the first time).
.venv/bin/python -m presim.outputs.ros2.tf2_build
echo "$hash" > "$stamp"
echo "setup.sh: .venv ready"
