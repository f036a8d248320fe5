#!/usr/bin/env bash
# Runs every test of compgate: formatting, lints, docs, unit, integration and doc tests of
# the whole workspace. Installs what it needs first. CI runs exactly this (.ci/run).
set -euo pipefail
cd "$(dirname "$0")"
# One build from scratch gains nothing from incremental data, which costs gigabytes.
export CARGO_INCREMENTAL=${CARGO_INCREMENTAL:-0}

# Rust components the checks use (present on a standard rustup toolchain).
rustup component add rustfmt clippy >/dev/null 2>&1 || true

# System tools the service tests use: systemd-analyze (unit exposure, offline) and
# mosquitto (a real MQTT broker on loopback), promtool and prometheus (package prometheus:
# check a real scrape of the metrics endpoint, and the shipped alerting rules against
# the gateway), chromium (headless: loads the live status page).
need=()
command -v systemd-analyze >/dev/null 2>&1 || need+=(systemd)
command -v mosquitto >/dev/null 2>&1 || [[ -x /usr/sbin/mosquitto ]] || need+=(mosquitto)
command -v promtool >/dev/null 2>&1 || need+=(prometheus)
command -v chromium >/dev/null 2>&1 || need+=(chromium)
# openssl: the certificates of the TLS broker behind the shipped MQTT bridge.
command -v openssl >/dev/null 2>&1 || need+=(openssl)
# LinuxCNC (uspace, runs without a realtime kernel): the real control at the end of the
# chain in tests/nc_linuxcnc.rs.
command -v linuxcnc >/dev/null 2>&1 || need+=(linuxcnc-uspace)
if ((${#need[@]})); then
    echo "== installing ${need[*]}"
    if [[ $(id -u) -eq 0 ]]; then sudo=(); else sudo=(sudo); fi
    "${sudo[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

# Independent protocol peers (OPC UA, S7, ADS servers, a Modbus device, a CANopen node) in a
# venv under target/.
tests/peers/install.sh

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets -- -D warnings
# The production binary (deploy/install.sh): without the simulator.
cargo clippy -p compgate --no-default-features -- -D warnings
echo "== cargo doc (broken links and bad doc markup are errors)"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet
echo "== cargo test, the VM stages beside it"
cargo test --workspace --all-targets --no-run
# Each VM stage installs what it needs, copies its binaries out of this build and packs
# its initramfs (one after the other: they share apt and the kernel cache), then boots
# in the background: the VMs (one core each under emulation) beside the tests (less
# than one of the two cores) took a clean-clone run from 24 minutes to 19-22. Their
# output is shown once the tests are done. Booting them before clippy was slower: clippy
# took 8 minutes beside them against 3 alone, and the tests would then run alone.
stages=(systemd vcan powerloss)
declare -A what=(
    [vcan]="vcan tests (CAN source and CANopen node; natively on vcan0, else in a VM)"
    [powerloss]="power-loss checks (a power cut while recording and after calibrate, in a VM)"
    [systemd]="systemd checks (deploy/install.sh and the unit under a real systemd, in a VM)"
)
prepare() {
    echo "== preparing the ${what[$1]%% (*}"
    "tests/$1/run.sh" prepare
    rm -f "target/$1/boot.rc"
}
# boot_bg STAGE...: boots the stages one after the other in a process group of their
# own (stopped with this script), each one's output in target/STAGE/boot.log and its
# exit status in target/STAGE/boot.rc.
boot_pids=()
stop_boots() {
    local p
    for p in "${boot_pids[@]}"; do kill -- "-$p" 2>/dev/null || true; done
}
trap stop_boots EXIT
boot_bg() {
    # shellcheck disable=SC2016 # expanded by the inner bash
    setsid bash -c 'for s; do rc=0; "tests/$s/run.sh" boot >"target/$s/boot.log" 2>&1 || rc=$?
        echo "$rc" >"target/$s/boot.rc"; done' _ "$@" &
    boot_pids+=($!)
}
# The systemd VM is the longest (8-11 minutes beside the tests; the last to end): it
# boots as soon as it is prepared. The other two take 4-5 minutes together.
prepare systemd
boot_bg systemd
prepare vcan
prepare powerloss
boot_bg vcan powerloss
cargo test --workspace --all-targets
cargo test --workspace --doc
echo "== waiting for the VM stages"
wait "${boot_pids[@]}" || true
failed=()
for s in "${stages[@]}"; do
    echo "== ${what[$s]}"
    cat "target/$s/boot.log"
    [[ $(cat "target/$s/boot.rc" 2>/dev/null) == 0 ]] || failed+=("$s")
done
if ((${#failed[@]})); then
    echo "FAILED: the VM stages ${failed[*]} (their output above)" >&2
    exit 1
fi
