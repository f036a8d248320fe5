#!/usr/bin/env bash
# Runs the vcan integration tests (the CAN source and the simulated CANopen node).
#
# - Where the kernel has vcan (a shop-floor PC with `vcan0` up), they run natively.
# - Elsewhere they run inside a small VM: a Debian kernel under QEMU's software
#   emulation, an initramfs with busybox, the CAN modules, can-utils and the test
#   binaries. Results come back over the serial console.
#
# Usage: tests/vcan/run.sh [prepare|boot] [--smoke]
#   prepare, boot   one phase only (tests/vm/lib.sh); none: both
#   --smoke   boot the VM and show `ip link` with vcan0 up, run no tests
#
# With CI set, any run in which the vcan tests did not run is a failure.
# Environment: VCAN_VM_TIMEOUT_S (default 1500) bounds the whole VM run;
# VCAN_TESTS narrows the test set; VM_PROFILE=release runs the release build
# (tests/vm/lib.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
SMOKE=0
[[ " $* " == *" --smoke "* ]] && SMOKE=1
TIMEOUT_S=${VCAN_VM_TIMEOUT_S:-1500}
WORK=$ROOT/target/vcan

VM_STAGE=vcan
VM_STAGE_WHAT="the vcan tests"
VM_SKIP_HINT="the CAN tests did NOT run; set up vcan0 or the VM tooling"
# shellcheck source=../vm/lib.sh
source "$ROOT/tests/vm/lib.sh"

# The test binaries that need vcan0; their vcan tests are #[ignore]d in a plain
# `cargo test` and run here with --ignored. Test target names are unique in the workspace.
TESTS=(
    can_vcan     # compgate
    canopen_vcan # compgate-plc
)
# VCAN_TESTS="test ..." narrows the set while iterating.
if [[ -n "${VCAN_TESTS:-}" ]]; then read -ra TESTS <<<"$VCAN_TESTS"; fi

build_tests() {
    local out=$WORK/tests.txt
    : >"$WORK/build.log"
    vm_build "$WORK/build.log" --message-format=json >"$WORK/build.json"
    : >"$out"
    for name in "${TESTS[@]}"; do
        # The test target's own executable (not the binaries built alongside it).
        grep "\"kind\":\\[\"test\"\\]" "$WORK/build.json" | grep "\"name\":\"$name\"" |
            grep -o '"executable":"[^"]*"' | cut -d'"' -f4 >>"$out" || true
    done
    if [[ $(wc -l <"$out") -ne ${#TESTS[@]} ]]; then
        tail -20 "$WORK/build.log" >&2
        echo "vcan: FAILED: cannot find the test binaries of ${TESTS[*]}" >&2
        exit 1
    fi
}

mkdir -p "$WORK"

# ---- native: the kernel has vcan
if [[ $SMOKE -eq 0 && -e /sys/class/net/vcan0 ]]; then
    echo "vcan: vcan0 exists, running natively"
    run_vm() { # natively: no VM
        ip link set up vcan0 2>/dev/null || true
        local rc=0 exe
        for exe in $(cat "$WORK/tests.txt"); do
            VCAN_IF=vcan0 "$exe" --ignored --test-threads=1 --show-output || rc=1
        done
        exit $rc
    }
    vm_prepares || vm_boot_only
    # The e2e test drives can-utils (cansend, candump, cangen) as a third-party peer.
    command -v cansend >/dev/null || vm_install "$WORK.apt.log" can-utils
    build_tests
    vm_prepared
    exit 0
fi

# ---- VM: boot, on what prepare left, and the results
run_vm() {
    LOG=$WORK/console.log
    echo "vcan: booting the VM (timeout ${TIMEOUT_S} s, console in target/vcan/console.log)"
    t0=$(date +%s.%N)
    set +e
    # -enable-kvm hangs on the build machines: software emulation it is.
    timeout "$TIMEOUT_S" qemu-system-x86_64 -accel tcg -m 1536 -smp 1 -nographic -no-reboot \
        -kernel "$KDIR/vmlinuz" -initrd "$WORK/initrd.gz" \
        -append "console=ttyS0 quiet panic=-1" </dev/null 2>&1 | tr -d '\r' | tee "$LOG"
    qrc=${PIPESTATUS[0]}
    set -e
    t1=$(date +%s.%N)
    wall=$(echo "$t1 - $t0" | bc 2>/dev/null || awk "BEGIN{print $t1-$t0}")
    [[ $qrc -eq 124 ]] && echo "vcan: the VM timed out after ${TIMEOUT_S} s" >&2

    grep -q 'VCAN-BOOTED' "$LOG" || { echo "vcan: FAILED: the VM did not boot" >&2; exit 1; }
    echo "vcan: VM $(grep -o 'VCAN-BOOTED: .*' "$LOG" | sed 's/VCAN-BOOTED: /booted with vcan0 up after /') of guest uptime; whole VM run ${wall%.*} s wall"
    if [[ $SMOKE -eq 1 ]]; then
        grep -q 'vcan0:.*UP' "$LOG" || { echo "vcan: FAILED: vcan0 not up" >&2; exit 1; }
        exit 0
    fi
    res=$(grep -o 'VCAN-RESULT: [0-9]* passed, [0-9]* failed' "$LOG" | tail -1 || true)
    [[ -n "$res" ]] || { echo "vcan: FAILED: no result line from the VM" >&2; exit 1; }
    passed=$(echo "$res" | awk '{print $2}')
    failed=$(echo "$res" | awk '{print $4}')
    # Individual tests, from the harness' own summary lines inside the VM.
    tp=$(grep -ao 'test result: [a-zA-Z]*\. [0-9]* passed; [0-9]* failed' "$LOG" | awk '{s+=$4} END{print s+0}')
    tf=$(grep -ao 'test result: [a-zA-Z]*\. [0-9]* passed; [0-9]* failed' "$LOG" | awk '{s+=$6} END{print s+0}')
    grep -ao 'CAN-BENCH: highest.*\|CAN e2e: .*' "$LOG" | sed 's/^/vcan: /' || true
    echo "vcan: test binaries: $passed of ${#TESTS[@]} passed; guest time $(grep -ao 'VCAN-RESULT: .*uptime [0-9.]* s' "$LOG" | grep -o '[0-9.]* s$')"
    echo "vcan: $tp passed, $tf failed"
    [[ $failed -eq 0 && $passed -eq ${#TESTS[@]} && $tp -gt 0 ]] || exit 1
}

vm_prepares || vm_boot_only

# ---- VM: prepare
need=()
command -v qemu-system-x86_64 >/dev/null || need+=(qemu-system-x86)
# A static busybox: the initramfs carries no libraries for it.
if [[ ! -x /bin/busybox ]] || ldd /bin/busybox >/dev/null 2>&1; then need+=(busybox-static); fi
command -v cpio >/dev/null || need+=(cpio)
command -v cansend >/dev/null || need+=(can-utils)
if [[ ${#need[@]} -gt 0 ]]; then vm_install "$WORK.apt.log" "${need[@]}"; fi

# ---- kernel and CAN modules, cached under target/vm-kernel
vm_kernel

# ---- initramfs
IR=$WORK/ir
rm -rf "$IR" && mkdir -p "$IR"/{bin,sbin,proc,sys,dev,mods,tmp,tests}
cp /bin/busybox "$IR/bin/"
for m in can can-raw can-bcm can-dev vcan; do cp "$KDIR/mods/$m.ko" "$IR/mods/"; done
carry "$IR" "$(command -v ip)" /sbin/ip
carry "$IR" "$(command -v cansend)" /bin/cansend
carry "$IR" "$(command -v candump)" /bin/candump
carry "$IR" "$(command -v cangen)" /bin/cangen

# The independent CANopen node (tests/peers/canopen_node.py): the peers' interpreter, its
# standard library without what no peer imports (tests, Tk, IDLE, other packages), and
# canopen with what it requires, each at the path it has here, so the test finds them
# as it does outside the VM.
carry_python() {
    local py=$ROOT/target/peers-venv/bin/python p next
    "$py" -c "import canopen" 2>/dev/null || return 0 # the test says what is missing
    mkdir -p "$IR$ROOT/target/peers-venv"
    cp "$ROOT/target/peers-venv/pyvenv.cfg" "$IR$ROOT/target/peers-venv/"
    p=$py
    while [[ -L $p ]]; do
        mkdir -p "$IR$(dirname "$p")" && cp -a "$p" "$IR$p"
        next=$(readlink "$p")
        [[ $next == /* ]] || next=$(dirname "$p")/$next
        p=$next
    done
    carry "$IR" "$p" "$p"
    local stdlib
    stdlib=$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["stdlib"])')
    tar -C / -cf - --exclude=test --exclude=site-packages --exclude=dist-packages \
        --exclude=idlelib --exclude=tkinter --exclude=turtledemo --exclude=ensurepip \
        --exclude=lib2to3 --exclude='config-3*' --exclude=pydoc_data --exclude='_tkinter*' "${stdlib#/}" |
        tar -C "$IR" -xf -
    for so in "$stdlib"/lib-dynload/*.so; do
        [[ $so == */_tkinter* ]] && continue
        for l in $(ldd "$so" 2>/dev/null | grep -o '/[^ ]*'); do
            [[ -e "$IR$l" ]] || { mkdir -p "$IR$(dirname "$l")" && cp -L "$l" "$IR$l"; }
        done
    done
    "$py" - <<'PY' | while read -r f; do mkdir -p "$IR$(dirname "$f")" && cp -L "$f" "$IR$f"; done
import importlib.metadata as md
from packaging.requirements import Requirement
todo, seen = ["canopen"], set()
while todo:
    dist = md.distribution(todo.pop())
    name = dist.metadata["Name"].lower()
    if name in seen:
        continue
    seen.add(name)
    for f in dist.files or []:
        path = dist.locate_file(f)
        if path.is_file():
            print(path.resolve())
    for r in map(Requirement, dist.requires or []):
        if r.marker is None or r.marker.evaluate({"extra": ""}):
            todo.append(r.name)
PY
    mkdir -p "$IR$ROOT/tests/peers"
    cp "$ROOT/tests/peers/canopen_node.py" "$IR$ROOT/tests/peers/"
}

RUN_TESTS=""
if [[ $SMOKE -eq 0 ]]; then
    carry_python
    echo "vcan: building the test binaries"
    i=0
    build_tests
    for exe in $(cat "$WORK/tests.txt"); do
        i=$((i + 1))
        carry "$IR" "$exe" "/tests/t$i"
        # Debug info only makes the initramfs (held in guest RAM) bigger.
        strip --strip-debug "$IR/tests/t$i" 2>/dev/null || true
        RUN_TESTS+="run_test t$i $(basename "$exe")"$'\n'
    done
fi

cat >"$IR/init" <<EOF
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin:/sbin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev
# No tmpfs over /tmp: the initramfs (itself writable) may carry the Python peers
# there, at the path of a checkout under /tmp.
export TMPDIR=/tmp
${CI:+export CI=1}
for m in can can-raw can-bcm can-dev vcan; do insmod /mods/\$m.ko || echo "VCAN-ERROR: insmod \$m"; done
ip link set up lo
ip link add dev vcan0 type vcan && ip link set up vcan0
echo "VCAN-BOOTED: \$(cut -d' ' -f1 /proc/uptime) s"
ip link show vcan0
passed=0; failed=0
run_test() {
    echo "VCAN-RUN: \$2"
    t0=\$(cut -d' ' -f1 /proc/uptime)
    if VCAN_IF=vcan0 RUST_BACKTRACE=1 /tests/\$1 --ignored --test-threads=1 --show-output; then
        passed=\$((passed+1)); r=ok
    else
        failed=\$((failed+1)); r=FAILED
    fi
    echo "VCAN-TEST: \$2 \$r from \$t0 s to \$(cut -d' ' -f1 /proc/uptime) s"
}
$RUN_TESTS
echo "VCAN-RESULT: \$passed passed, \$failed failed; uptime \$(cut -d' ' -f1 /proc/uptime) s"
poweroff -f
EOF
chmod +x "$IR/init"
(cd "$IR" && find . | cpio -o -H newc 2>/dev/null | gzip -1 >"$WORK/initrd.gz")

vm_prepared
