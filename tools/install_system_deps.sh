#!/usr/bin/env bash
# Install the Debian packages the AVR firmware tests need, only when missing:
# the Uno tool chain (gcc-avr, avr-libc, arduino-core-avr), simavr and its
# headers (the emulated ATmega328P; GPL-3, used locally, never shipped) and
# avrdude (flashing a real Uno). Runs apt-get update first; needs root or sudo.
set -euo pipefail
PACKAGES=(gcc-avr avr-libc arduino-core-avr simavr libsimavr-dev libsimavrparts1 avrdude)
missing=()
for pkg in "${PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
        missing+=("$pkg")
    fi
done
if [ ${#missing[@]} -eq 0 ]; then
    exit 0
fi
if ! command -v apt-get >/dev/null; then
    echo "install_system_deps: not a Debian system; install: ${missing[*]}" >&2
    exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO="sudo"
fi
echo "install_system_deps: installing ${missing[*]}" >&2
$SUDO apt-get update -q
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q "${missing[@]}"
