#!/usr/bin/env bash
# A real power cut while the gateway records: what the recorder committed and what
# `compgate calibrate` wrote must be on the disk after the reboot.
#
# Two boots of a small VM (a Debian kernel under QEMU's software emulation, this
# machine's root read-only over virtio 9p under a tmpfs overlay, as in the systemd
# stage) on one ext4 disk image, created fresh under target/powerloss:
# - boot 1 (tests/powerloss/guest.sh 1) runs the simulated plant and the gateway
#   recording to the disk (commit_interval_s = 0.5) for about 15 s, writes a model
#   with `compgate calibrate --out` to a new file on the disk (and the same model to
#   a tmpfs), and about 1 s later cuts the power (sysrq b: an immediate reset, nothing
#   written back or synced);
# - boot 2 (guest.sh 2) checks the database (integrity_check ok, its newest reading
#   within commit_interval_s + 1 s of the cut), the model (byte-identical to the tmpfs
#   copy, whose checksum boot 1 printed on the console), that the gateway starts again
#   and records, and that a file system gone read-only is named in its error;
# - the host compares what a subscriber got from the gateway's MQTT outbox in each
#   boot: only the messages of the last commit_interval_s + 1 s may come again.
# Results come back over the serial console: one PL-CHECK line per check.
#
# Usage: tests/powerloss/run.sh [prepare|boot]   (the phases: tests/vm/lib.sh; none: both)
# With CI set, a run in which the checks did not run is a failure.
# Environment: POWERLOSS_VM_TIMEOUT_S (default 120) bounds each boot.
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
TIMEOUT_S=${POWERLOSS_VM_TIMEOUT_S:-120}
WORK=$ROOT/target/powerloss
mkdir -p "$WORK"
t_start=$(date +%s)

VM_STAGE=powerloss
VM_STAGE_WHAT="the power-loss checks"
# shellcheck source=../vm/lib.sh
source "$ROOT/tests/vm/lib.sh"

# ---- boot: the two boots, on what prepare left, and the results
boot_phase() {
    local phase=$1 log=$WORK/console-$1.log
    echo "powerloss: boot $phase (console in target/powerloss/console-$phase.log)"
    set +e
    timeout "$TIMEOUT_S" qemu-system-x86_64 -accel tcg -m 2048 -smp 1 -nographic -no-reboot \
        -serial mon:stdio \
        -drive file="$WORK/disk.img",format=raw,if=virtio \
        -fsdev local,id=hostroot,path=/,security_model=passthrough,readonly=on,multidevs=remap \
        -device virtio-9p-pci,fsdev=hostroot,mount_tag=hostroot \
        -kernel "$KDIR/vmlinuz" -initrd "$WORK/initrd.gz" \
        -append "console=ttyS0 quiet panic=-1 pl.phase=$phase" \
        </dev/null 2>&1 | stdbuf -oL tr -d '\r' >"$log"
    local qrc=${PIPESTATUS[0]}
    set -e
    [[ $qrc -eq 124 ]] && echo "powerloss: boot $phase timed out after ${TIMEOUT_S} s" >&2
    grep -q 'PL-BOOTED' "$log" || { echo "powerloss: FAILED: boot $phase did not boot" >&2; exit 1; }
    grep -a 'PL-ERROR' "$log" >&2 && { echo "powerloss: FAILED: boot $phase" >&2; exit 1; }
    grep -a '^PL-[A-Z0-9]*:' "$log" | grep -v '^PL-BOOTED\|^PL-PHASE-END\|^PL-MSG' | sed 's/^/powerloss: /' || true
}

run_vm() {
    # A fresh disk: nothing of an earlier run is taken for this one's.
    rm -f "$WORK/disk.img" "$WORK/boot1.txt"
    truncate -s 256M "$WORK/disk.img"
    mkfs.ext4 -q -F "$WORK/disk.img"
    boot_phase 1
    # Boot 1 ends with the power cut: no PL-PHASE-END. What boot 2 compares with comes
    # from its console (its tmpfs is gone).
    grep -a '^PL-CUT:' "$WORK/console-1.log" >"$WORK/boot1.txt" ||
        { echo "powerloss: FAILED: boot 1 did not reach the power cut" >&2; exit 1; }
    ! grep -aq 'PL-PHASE-END' "$WORK/console-1.log" ||
        { echo "powerloss: FAILED: boot 1 ended without the power cut" >&2; exit 1; }
    boot_phase 2

    # The MQTT outbox: a message boot 1's subscriber got and boot 2 published again was
    # sent before the cut, but its deletion from the outbox was not on the disk. Only the
    # messages of the last commit_interval_s + 1 s may come again, as only the readings of
    # that span may be lost.
    read -r _ cut _ <"$WORK/boot1.txt"
    msgs() { grep -a '^PL-MSG: ' "$WORK/console-$1.log" | cut -d' ' -f2- | sort -u; }
    msgs 1 >"$WORK/mqtt-1.txt"
    msgs 2 >"$WORK/mqtt-2.txt"
    again=$(comm -12 "$WORK/mqtt-1.txt" "$WORK/mqtt-2.txt")
    n_again=$(grep -c . <<<"$again" || true)
    oldest=$(awk -v cut="$cut" 'NF { a = cut - $2; if (a > m) m = a } END { print m + 0 }' <<<"$again")
    detail="boot 1's subscriber got $(grep -c . "$WORK/mqtt-1.txt") messages, boot 2's $(grep -c . "$WORK/mqtt-2.txt"); $n_again published again, the oldest $oldest ms before the cut (at most 1500)"
    mqtt_ok=0
    if [[ ! -s $WORK/mqtt-1.txt || $(comm -13 "$WORK/mqtt-1.txt" "$WORK/mqtt-2.txt" | grep -c .) -eq 0 ]]; then
        echo "powerloss: PL-CHECK: FAILED: the outbox publishes again at most the last commit_interval_s + 1 s: no messages to compare: $detail"
    elif ((oldest > 1500)); then
        echo "powerloss: PL-CHECK: FAILED: the outbox publishes again at most the last commit_interval_s + 1 s: $detail"
    else
        echo "powerloss: PL-CHECK: ok: the outbox publishes again at most the last commit_interval_s + 1 s: $detail"
        mqtt_ok=1
    fi

    res=$(grep -ao 'PL-RESULT: [0-9]* passed, [0-9]* failed' "$WORK/console-2.log" | tail -1 || true)
    echo "powerloss: whole stage $(($(date +%s) - t_start)) s wall"
    [[ -n "$res" ]] || { echo "powerloss: FAILED: no result line from boot 2" >&2; exit 1; }
    passed=$(($(echo "$res" | awk '{print $2}') + mqtt_ok))
    failed=$(($(echo "$res" | awk '{print $4}') + 1 - mqtt_ok))
    echo "powerloss: $passed passed, $failed failed"
    ((failed == 0)) || exit 1
}

vm_prepares || vm_boot_only

# ---- prepare
need=()
command -v qemu-system-x86_64 >/dev/null || need+=(qemu-system-x86)
if [[ ! -x /bin/busybox ]] || ldd /bin/busybox >/dev/null 2>&1; then need+=(busybox-static); fi
command -v cpio >/dev/null || need+=(cpio)
command -v mkfs.ext4 >/dev/null || need+=(e2fsprogs)
# What guest.sh uses, from this machine's root.
command -v sqlite3 >/dev/null || need+=(sqlite3)
command -v mosquitto_sub >/dev/null || need+=(mosquitto-clients)
[[ -x /usr/sbin/mosquitto ]] || need+=(mosquitto)
if [[ ${#need[@]} -gt 0 ]]; then vm_install "$WORK/apt.log" "${need[@]}"; fi
vm_kernel

# The gateway and the simulated plant: the build the vcan stage ran (the same build:
# nothing to do after it), put aside (the systemd stage builds the production binary at
# the same path) and stripped (read over 9p under emulation).
echo "powerloss: building the gateway"
: >"$WORK/build.log"
vm_build "$WORK/build.log" >/dev/null
install -s -D "$VM_BIN_DIR/compgate" "$WORK/compgate"

# The gateway's config: the demo plant at fixed ports, recording to the disk. A
# measurement CSV for calibrate: K0 growing with T_a and the position.
awk '/"127.0.0.1:0"/ { sub(/"127.0.0.1:0"/, "\"127.0.0.1:1502" n++ "\"") } 1' config/demo.toml >"$WORK/gw.toml"
[[ $(grep -c '"127.0.0.1:1502[01]"' "$WORK/gw.toml") -eq 2 ]] ||
    { echo "powerloss: FAILED: config/demo.toml has not the two addresses expected" >&2; exit 1; }
printf '\n[recorder]\npath = "/data/rec/compgate.db"\ncommit_interval_s = 0.5\n' >>"$WORK/gw.toml"
printf '\n[mqtt]\nbroker = "127.0.0.1:18830"\nmachine = "m1"\npublish_interval_s = 0.5\n' >>"$WORK/gw.toml"
awk 'BEGIN { print "t_s,pos_mm,err_um,T_a,T_b"; t = 0
    for (r = 0; r < 60; r++) for (k = 0; k < 9; k++) {
        p = k * 250; t += 10; ta = 20 + t / 600; tb = 22 + 3 * sin(t / 400)
        printf "%d,%d,%.4f,%.4f,%.4f\n", t, p, 5 * (ta - 20) + 0.01 * p + 0.3 * sin(t * 7.1), ta, tb } }' \
    >"$WORK/m.csv"

# ---- initramfs: the disk at /data, this machine's root read-only with a tmpfs over
# it, a tmpfs at /run; guest.sh in a chroot, then power off
IR=$WORK/ir
rm -rf "$IR" && mkdir -p "$IR"/{bin,proc,sys,dev,mods,lower,rw,newroot}
cp /bin/busybox "$IR/bin/"
# In load order.
MODS="crc16 crc32c_generic libcrc32c mbcache jbd2 ext4 virtio_ring virtio
    virtio_pci_legacy_dev virtio_pci_modern_dev virtio_pci virtio_blk netfs fscache
    9pnet 9pnet_virtio 9p overlay"
for m in $MODS; do cp "$KDIR/mods/$m.ko" "$IR/mods/"; done
cat >"$IR/init" <<EOF
#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
ln -s /proc/self/fd /dev/fd
ip link set lo up
for m in $(echo $MODS); do insmod /mods/\$m.ko || echo "PL-ERROR: insmod \$m"; done
checkout=$ROOT
EOF
cat >>"$IR/init" <<'EOF'
mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=524288 hostroot /lower || echo "PL-ERROR: 9p"
mount -t tmpfs -o size=1g tmpfs /rw && mkdir -p /rw/upper /rw/work
mount -t overlay -o lowerdir=/lower,upperdir=/rw/upper,workdir=/rw/work overlay /newroot ||
    echo "PL-ERROR: overlay"
mkdir -p /newroot/data
# errors=remount-ro: what a disk error does to the file system (guest.sh triggers one).
mount -t ext4 -o errors=remount-ro /dev/vda /newroot/data || echo "PL-ERROR: ext4 mount"
mount -t proc proc /newroot/proc; mount -t sysfs sys /newroot/sys; mount --bind /dev /newroot/dev
mount -t tmpfs -o mode=0755 tmpfs /newroot/run
phase=$(sed -n 's/.*pl\.phase=\([0-9]\).*/\1/p' /proc/cmdline)
echo "PL-BOOTED: phase $phase at $(cut -d' ' -f1 /proc/uptime) s"
chroot /newroot /bin/bash "$checkout/tests/powerloss/guest.sh" "$phase" "$checkout"
echo "PL-PHASE-END: $phase"
umount /newroot/data 2>/dev/null
poweroff -f
EOF
chmod +x "$IR/init"
(cd "$IR" && find . | cpio -o -H newc 2>/dev/null | gzip -1 >"$WORK/initrd.gz")

vm_prepared
