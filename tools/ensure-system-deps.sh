#!/usr/bin/env bash
# Debian packages the install needs:
# - libusb-1.0-0: open3d loads libusb-1.0 at import time;
# - libembree-dev (Embree 3 headers and library) and g++: the compiled tracer core, built by pip.
set -euo pipefail
missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
[ -f /usr/include/embree3/rtcore.h ] || missing+=(libembree-dev)
command -v g++ >/dev/null || missing+=(g++)
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
echo "installing Debian packages: ${missing[*]}"
SUDO=""
if [ "$(id -u)" != "0" ]; then
  if command -v sudo >/dev/null; then SUDO="sudo"; else
    echo "error: ${missing[*]} missing and this user is not root; install them: apt-get install ${missing[*]}" >&2
    exit 1
  fi
fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get install -y -q "${missing[@]}" >/dev/null 2>&1 || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q "${missing[@]}" >/dev/null; }
