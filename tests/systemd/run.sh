#!/usr/bin/env bash
# Installs and runs compgate under a real systemd: deploy/install.sh, the unit's
# sandbox, Type=notify and STATUS=, the journal, reload, the watchdog and stop
# (tests/systemd/check.sh says what is checked).
#
# The build machines run no systemd, so the checks run in a small VM: a Debian kernel
# under QEMU's software emulation whose root is this machine's own, read-only over
# virtio 9p under a tmpfs overlay, booted with systemd as PID 1 into a target that
# runs check.sh and powers off. Results come back over the serial console.
#
# Usage: tests/systemd/run.sh [prepare|boot]   (the phases: tests/vm/lib.sh; none: both)
# With CI set, a run in which the checks did not run is a failure.
# Environment: SYSTEMD_VM_TIMEOUT_S (default 1500) bounds the VM run; VM_PROFILE=release
# runs the release build (tests/vm/lib.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
TIMEOUT_S=${SYSTEMD_VM_TIMEOUT_S:-1500}
WORK=$ROOT/target/systemd
mkdir -p "$WORK"

VM_STAGE=systemd
VM_STAGE_WHAT="the systemd checks"
# shellcheck source=../vm/lib.sh
source "$ROOT/tests/vm/lib.sh"

# ---- boot: the VM, on what prepare left, and its results
run_vm() {
    LOG=$WORK/console.log
    echo "systemd: booting the VM (timeout ${TIMEOUT_S} s, console in target/systemd/console.log)"
    t0=$(date +%s)
    set +e
    # Serial ports for check.sh: a second 16550 UART (ttyS1) and a virtio console (hvc0),
    # a driver group the unit does not allow; what they send is discarded. One vCPU: with
    # two the VM ran alone in 245 s against 499 s, but beside ./test.sh's `cargo test` in
    # 873 s against 621 s, and slowed the tests as well.
    timeout "$TIMEOUT_S" qemu-system-x86_64 -accel tcg -m 3072 -smp 1 -nographic -no-reboot \
        -serial mon:stdio -serial null \
        -device virtio-serial-pci -chardev null,id=hvc -device virtconsole,chardev=hvc \
        -fsdev local,id=hostroot,path=/,security_model=passthrough,readonly=on,multidevs=remap \
        -device virtio-9p-pci,fsdev=hostroot,mount_tag=hostroot \
        -kernel "$KDIR/vmlinuz" -initrd "$WORK/initrd.gz" \
        -append "console=ttyS0 quiet panic=-1 systemd.unit=compgate-check.target systemd.show_status=false" \
        </dev/null 2>&1 | stdbuf -oL tr -d '\r' | tee "$LOG"
    qrc=${PIPESTATUS[0]}
    set -e
    echo "systemd: VM run $(($(date +%s) - t0)) s wall"
    [[ $qrc -eq 124 ]] && echo "systemd: the VM timed out after ${TIMEOUT_S} s" >&2
    grep -q 'SD-BOOTED' "$LOG" || { echo "systemd: FAILED: the VM did not boot" >&2; exit 1; }
    res=$(grep -ao 'SD-RESULT: [0-9]* passed, [0-9]* failed' "$LOG" | tail -1 || true)
    [[ -n "$res" ]] || { echo "systemd: FAILED: no result line from the VM" >&2; exit 1; }
    echo "systemd: ${res#SD-RESULT: }"
    failed=$(echo "$res" | awk '{print $4}')
    [[ $failed -eq 0 ]] || { grep -a 'SD-CHECK: FAILED' "$LOG" >&2; exit 1; }
}

vm_prepares || vm_boot_only

# ---- prepare
need=()
command -v qemu-system-x86_64 >/dev/null || need+=(qemu-system-x86)
if [[ ! -x /bin/busybox ]] || ldd /bin/busybox >/dev/null 2>&1; then need+=(busybox-static); fi
command -v cpio >/dev/null || need+=(cpio)
# What the VM boots and check.sh uses, from this machine's root.
[[ -x /lib/systemd/systemd ]] || need+=(systemd)
command -v sqlite3 >/dev/null || need+=(sqlite3)
command -v curl >/dev/null || need+=(curl)
command -v socat >/dev/null || need+=(socat)
command -v ss >/dev/null || need+=(iproute2)
if [[ ${#need[@]} -gt 0 ]]; then vm_install "$WORK/apt.log" "${need[@]}"; fi
vm_kernel

# The binary install.sh installs: it builds it itself where cargo is on the PATH, which
# the VM's systemd does not have, and otherwise takes target/production's. Built here
# as install.sh builds it (in VM_PROFILE) but in the shared target directory, whose
# dependencies the test build has built already. Both stripped of their line tables
# (70 MB to 38 MB in debug, 110 MB to 20 MB in release): the update checks copy the
# binary over the VM's 9p root several times, slow under emulation; the code is the
# same. The simulated plant is the build the vcan stage ran (nothing to do after it),
# put aside first.
echo "systemd: building the production binary and the simulator"
: >"$WORK/build.log"
vm_build "$WORK/build.log" >/dev/null
install -s -D "$VM_BIN_DIR/compgate" "$WORK/plant/compgate"
cargo build "${VM_CARGO_PROFILE[@]}" --no-default-features --bin compgate --locked >>"$WORK/build.log" 2>&1 ||
    { tail -20 "$WORK/build.log" >&2; echo "systemd: FAILED: build" >&2; exit 1; }
install -s -D "$VM_BIN_DIR/compgate" target/production/release/compgate

# ---- initramfs: mount this machine's root read-only with a tmpfs over it, add the
# check's units, hand over to systemd
IR=$WORK/ir
rm -rf "$IR" && mkdir -p "$IR"/{bin,proc,sys,dev,mods,lower,rw,newroot,units}
cp /bin/busybox "$IR/bin/"
# In load order.
MODS="virtio_ring virtio virtio_pci_legacy_dev virtio_pci_modern_dev virtio_pci netfs fscache
    9pnet 9pnet_virtio 9p overlay virtio_console"
for m in $MODS; do cp "$KDIR/mods/$m.ko" "$IR/mods/"; done
cat >"$IR/units/compgate-check.service" <<EOF
[Unit]
Description=compgate under systemd: tests/systemd/check.sh
After=basic.target
SuccessAction=poweroff-force
FailureAction=poweroff-force

[Service]
Type=oneshot
ExecStart=/bin/bash $ROOT/tests/systemd/check.sh
StandardOutput=journal+console
StandardError=journal+console
EOF
cat >"$IR/units/compgate-check.target" <<'EOF'
[Unit]
Description=compgate under systemd
Requires=basic.target compgate-check.service
After=basic.target compgate-check.service
EOF
cat >"$IR/init" <<EOF
#!/bin/busybox sh
/bin/busybox --install -s /bin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
for m in $(echo $MODS); do insmod /mods/\$m.ko || echo "SD-ERROR: insmod \$m"; done
checkout=$ROOT
EOF
cat >>"$IR/init" <<'EOF'
mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=524288 hostroot /lower || echo "SD-ERROR: 9p"
mount -t tmpfs -o size=2g tmpfs /rw && mkdir -p /rw/upper /rw/work
mount -t overlay -o lowerdir=/lower,upperdir=/rw/upper,workdir=/rw/work overlay /newroot ||
    echo "SD-ERROR: overlay"
cp /units/* /newroot/etc/systemd/system/
# This machine's state is not the guest's: no mounts from its fstab, a fresh machine id,
# empty /tmp and /run, and no container marker (systemd would take its arguments from
# its command line alone and skip what a container does not do). No generators: the
# guest needs none (no fstab, getty, SysV scripts or disks to find), and systemd runs
# each at every daemon-reload, which install.sh and the checks do many times (a reload
# took 15 s with them, 12 s without, under emulation).
: >/newroot/etc/fstab
rm -f /newroot/usr/lib/systemd/system-generators/* /newroot/lib/systemd/system-generators/*
rm -f /newroot/etc/machine-id /newroot/.dockerenv && : >/newroot/etc/machine-id
for d in tmp var/tmp; do mount -t tmpfs -o mode=1777 tmpfs /newroot/$d; done
mount -t tmpfs -o mode=0755 tmpfs /newroot/run
# The checkout check.sh runs from may lie under one of those (a clone in /tmp).
mkdir -p "/newroot$checkout" && mount --bind "/lower$checkout" "/newroot$checkout"
echo "SD-BOOTED: $(cut -d' ' -f1 /proc/uptime) s"
umount /proc /sys
mount --move /dev /newroot/dev 2>/dev/null || umount /dev
exec switch_root /newroot /lib/systemd/systemd
EOF
chmod +x "$IR/init"
(cd "$IR" && find . | cpio -o -H newc 2>/dev/null | gzip -1 >"$WORK/initrd.gz")

vm_prepared
