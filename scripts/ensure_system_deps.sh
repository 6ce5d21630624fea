#!/usr/bin/env bash
# Installs the system libraries linereg needs (Open3D loads libusb-1.0 at import time).
set -euo pipefail

if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    exit 0
fi
if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "linereg: installing libusb-1.0-0 (needed by Open3D) with apt-get"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
    exit 0
fi
echo "linereg: Open3D needs the system library libusb-1.0 and it is missing." >&2
echo "  Debian/Ubuntu: sudo apt-get install libusb-1.0-0" >&2
echo "  Fedora:        sudo dnf install libusb1" >&2
exit 1
