#!/usr/bin/env bash
# Debian packages the install needs (the same names on Debian 12 and 13):
# - libusb-1.0-0, libegl1, libgl1, libx11-6: open3d's module links them (a minimal Debian 13 has
#   none of them; checked with ldd in a debootstrap of trixie);
# - libembree-dev (Embree 3 on Debian 12, Embree 4 on 13) and g++: the compiled tracer core, built
#   by pip.
set -euo pipefail
missing=()
for lib in libusb-1.0.so.0:libusb-1.0-0 libEGL.so.1:libegl1 libGL.so.1:libgl1 libX11.so.6:libx11-6; do
  ldconfig -p 2>/dev/null | grep -q "${lib%%:*}" || missing+=("${lib##*:}")
done
[ -f /usr/include/embree3/rtcore.h ] || [ -f /usr/include/embree4/rtcore.h ] || missing+=(libembree-dev)
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
