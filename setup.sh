#!/usr/bin/env bash
# Fresh-machine setup for mcl3d on Debian/Ubuntu, then one job:
#   bash setup.sh demo    # simulate a short log, inspect it (the demo grows with the project)
#   bash setup.sh test    # run the test suite on the cpu backend
#   bash setup.sh         # set up only; then use .venv/bin/mcl3d
# It installs the system libraries open3d and the Vulkan backend need (apt, as root or via
# sudo), creates .venv with a supported Python (3.10-3.13) and installs mcl3d into it.
set -euo pipefail
cd "$(dirname "$0")"

SYSTEM_PACKAGES=(libusb-1.0-0 libgl1 libegl1 libx11-6 libgomp1 libvulkan1 mesa-vulkan-drivers)

say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }

missing_packages() {
  local missing=() pkg
  for pkg in "$@"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
  done
  echo "${missing[@]:-}"
}

apt_install() {
  local cmd=(apt-get install -y --no-install-recommends "$@")
  if [ "$(id -u)" -eq 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive "${cmd[@]}" -qq >/dev/null
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive "${cmd[@]}" -qq >/dev/null
  else
    echo "mcl3d needs these system packages: $*" >&2
    echo "run: sudo apt-get update && sudo ${cmd[*]}" >&2
    exit 1
  fi
}

pick_python() {
  local candidate
  for candidate in "${PYTHON:-}" python3.13 python3.12 python3.11 python3.10 python3; do
    [ -n "$candidate" ] && command -v "$candidate" >/dev/null || continue
    if "$candidate" -c 'import sys; sys.exit(not ((3, 10) <= sys.version_info[:2] <= (3, 13)))' 2>/dev/null; then
      echo "$candidate"; return 0
    fi
  done
  echo "mcl3d needs Python 3.10-3.13 (taichi 1.7.4 has no wheels for newer ones); set PYTHON=/path/to/python3.x" >&2
  exit 1
}

if command -v dpkg-query >/dev/null; then
  read -r -a missing <<<"$(missing_packages "${SYSTEM_PACKAGES[@]}")"
  if [ "${#missing[@]}" -gt 0 ]; then
    say "installing system packages: ${missing[*]}"
    apt_install "${missing[@]}"
  fi
else
  say "not a Debian/Ubuntu system: make sure libusb-1.0, libGL/EGL and a Vulkan loader are installed"
fi

python=$(pick_python)
if [ ! -x .venv/bin/python ]; then
  say "creating .venv with $($python --version)"
  if ! "$python" -m venv .venv 2>/dev/null; then
    rm -rf .venv
    apt_install "python3-venv"
    "$python" -m venv .venv
  fi
fi

stamp=.venv/.mcl3d-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  say "installing mcl3d and its dependencies into .venv (first time: a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[test]"
  echo "$want" >"$stamp"
fi

job="${1:-}"
[ $# -gt 0 ] && shift
case "$job" in
  "") say "ready: .venv/bin/mcl3d --help" ;;
  demo) exec .venv/bin/mcl3d demo "$@" ;;
  # two workers, a test file each at a time (module fixtures stay shared): most of a cold
  # run is Taichi compiling kernels, one core per process
  test) exec .venv/bin/python -m pytest -n 2 --dist loadfile "$@" ;;
  *) echo "usage: bash setup.sh [demo|test] [args...]" >&2; exit 2 ;;
esac
