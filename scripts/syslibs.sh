#!/usr/bin/env bash
# open3d's Linux wheel links against libusb-1.0; a fresh Debian machine lacks it and `import open3d`
# then fails. Install it when we can (root + apt-get); otherwise say exactly what to do.
set -eu
if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then exit 0; fi
if [ "$(uname -s)" != "Linux" ]; then exit 0; fi
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "ofjax: installing the system library libusb-1.0 (needed by open3d)"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
else
  echo "ofjax: open3d needs the system library libusb-1.0; install it (Debian/Ubuntu: sudo apt-get install libusb-1.0-0) and run make again" >&2
  exit 2
fi
