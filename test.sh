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
echo "== cargo test --no-run, then the VM stages in the background"
cargo test --workspace --all-targets --no-run
# Each VM stage installs what it needs, copies its binaries out of this build and packs
# its initramfs, then boots in the background (a process group of its own, stopped with
# this script) while the lints, the docs and the tests run: the VMs keep one core each
# busy under emulation, the tests less than one of the two, and the lints leave one idle
# while the crates at the top of the graph compile. Preparations run one after the other
# (they share apt and the kernel cache); the systemd VM, the longest, boots first. A
# boot runs no cargo and reads nothing of target/debug. Each stage's output is in
# target/STAGE/boot.log, its exit status in target/STAGE/boot.rc, shown at the end.
stages=(systemd vcan powerloss)
declare -A what=(
    [vcan]="vcan tests (CAN source and CANopen node; natively on vcan0, else in a VM)"
    [powerloss]="power-loss checks (a power cut while recording and after calibrate, in a VM)"
    [systemd]="systemd checks (deploy/install.sh and the unit under a real systemd, in a VM)"
)
boot_pids=()
stop_boots() {
    local p
    for p in "${boot_pids[@]}"; do kill -- "-$p" 2>/dev/null || true; done
}
trap stop_boots EXIT
# prepare_and_boot STAGE...: prepares the stages, then boots them one after the other.
prepare_and_boot() {
    for s; do
        echo "== preparing the ${what[$s]%% (*}"
        "tests/$s/run.sh" prepare
        rm -f "target/$s/boot.rc"
    done
    # shellcheck disable=SC2016 # expanded by the inner bash
    setsid bash -c 'for s; do rc=0; "tests/$s/run.sh" boot >"target/$s/boot.log" 2>&1 || rc=$?
        echo "$rc" >"target/$s/boot.rc"; done' _ "$@" &
    boot_pids+=($!)
}
prepare_and_boot systemd
prepare_and_boot vcan powerloss
echo "== cargo clippy"
cargo clippy --workspace --all-targets -- -D warnings
# The production binary (deploy/install.sh): without the simulator.
cargo clippy -p compgate --no-default-features -- -D warnings
echo "== cargo doc (broken links and bad doc markup are errors)"
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --quiet
echo "== cargo test"
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
