#!/usr/bin/env bash
# Set up bonesim on a fresh Debian machine: system packages, a virtual
# environment in .venv, and the package itself (an editable install: the
# command and the tests import the same files, so numba compiles them once).
#   scripts/setup.sh          runtime only
#   scripts/setup.sh --test   plus the test tools
set -euo pipefail
cd "$(dirname "$0")/.."
extras=""
if [ "${1:-}" = "--test" ]; then extras="[test]"; fi
if command -v apt-get >/dev/null 2>&1; then
  sudo=""
  if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
  $sudo apt-get update -qq
  # Python >= 3.11 with venv (Debian 12 ships 3.11); Mesa's software OpenGL
  # (EGL, OSMesa, GLX) and Xvfb for the window with or without a display;
  # PortAudio for sound (bonesim falls back to silence without a device).
  $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    python3 python3-venv python3-pip \
    libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libglx-mesa0 libosmesa6 \
    libx11-6 libxcursor1 libxrender1 libxt6 xvfb xauth \
    libportaudio2 >/dev/null
  # the tests build a stub of the OpenHaptics HD library (tests/bonesim/devices)
  if [ -n "${extras}" ]; then
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      gcc libc6-dev >/dev/null
  fi
fi
python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# --no-compile: the packages' byte code is compiled below, on both cores,
# while the kernels compile (pip compiles it file by file on one)
.venv/bin/python -m pip install -q --no-compile -e ".${extras}"
# an earlier non-editable install replaced by it leaves numba's caches in
# site-packages: those folders would shadow the editable package
for pkg in bonesim metrics ct_cases burrs; do
  for dir in .venv/lib/python3*/site-packages/"$pkg"; do
    if [ -d "$dir" ] && [ ! -e "$dir/__init__.py" ]; then rm -rf "$dir"; fi
  done
done
# The packages' byte code, in the background. A file that does not compile
# (a package's test data) is skipped, as pip would skip it: compileall's
# status is not the set-up's.
.venv/bin/python -m compileall -q -j 0 .venv/lib/python3*/site-packages >/dev/null 2>&1 &
bytecode=$!
# Compile the numba kernels once, here, rather than in the first run's four
# processes at once; the cache lies beside the sources, which the command and
# the tests share, so the second set-up finds it warm.
.venv/bin/bonesim warmup
wait "$bytecode" || true
echo "bonesim installed in $(pwd)/.venv"
