#!/bin/sh
# The toolchain of benchmarks/throughput/firmware_target.py and of the Cortex-M4F test in
# tests/test_firmware.py: Debian's cross compiler for bare-metal ARM with newlib (the C
# library and libm of the Cortex-M multilibs, hard-float included) and QEMU's system
# emulator for ARM (machines mps2-an386, Cortex-M4, and mps2-an500, Cortex-M7).
# Debian or Ubuntu; run as root or as a user who may sudo.
set -eu
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    SUDO=sudo
fi
$SUDO apt-get update
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
    gcc-arm-none-eabi binutils-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm
arm-none-eabi-gcc --version | head -n 1
qemu-system-arm --version | head -n 1
