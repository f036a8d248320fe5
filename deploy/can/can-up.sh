#!/bin/sh
# Brings up a CAN interface for compgate.
#
#   can-up.sh can0 [BITRATE]   a real controller (SocketCAN driver), default 500000 bit/s
#   can-up.sh vcan0            a virtual bus for dry runs and tests (module vcan)
#
# Needs root (or CAP_NET_ADMIN). The systemd-networkd files beside this script do the
# same at boot.
set -eu
IF=${1:?usage: can-up.sh IFACE [BITRATE]}
case "$IF" in
vcan*)
    modprobe vcan 2>/dev/null || true
    ip link show "$IF" >/dev/null 2>&1 || ip link add dev "$IF" type vcan
    ip link set up "$IF"
    ;;
*)
    BITRATE=${2:-500000}
    ip link set "$IF" down 2>/dev/null || true
    # restart-ms: recover from bus-off by itself after 100 ms.
    ip link set "$IF" type can bitrate "$BITRATE" restart-ms 100
    # A deeper transmit queue than the default 10 frames for SYNC bursts.
    ip link set "$IF" txqueuelen 1000
    ip link set up "$IF"
    ;;
esac
ip -details link show "$IF"
