#!/usr/bin/env bash
# Set up mvtop on a fresh Debian/Ubuntu machine with Python >= 3.10:
#   1. system libraries for offscreen OpenGL over EGL (pyrender), installed with apt-get if missing;
#   2. a virtual environment in .venv with mvtop, its test extras and the ray extra (--ray), at the
#      exact versions of constraints/pythonX.Y.txt where there is one for the venv's Python.
# Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 python3-venv)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" -eq 0 ]; then sudo=""; elif command -v sudo >/dev/null; then sudo="sudo"; else
    echo "setup: missing system packages: ${missing[*]} (install them with apt-get as root)" >&2; exit 1
  fi
  echo "setup: installing system packages: ${missing[*]}"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  python3 -m venv .venv
fi
lock="constraints/python$(.venv/bin/python -c 'import sys; print("%d.%d" % sys.version_info[:2])').txt"
constraint=()
if [ -f "$lock" ]; then
  constraint=(-c "$lock")
else
  echo "setup: no $lock for this Python: installing the newest releases pyproject.toml allows"
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check ${constraint[@]+"${constraint[@]}"} -e '.[test,ray]'
echo "setup: ready (.venv/bin/mvtop)"
