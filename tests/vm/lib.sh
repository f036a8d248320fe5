# Sourced by the scripts that boot a test VM (tests/vcan/run.sh, tests/systemd/run.sh,
# tests/powerloss/run.sh): their phases, a stage that cannot run, installing what a
# stage needs, a Debian kernel with the modules they load, and carrying a program into
# an initramfs. The caller sets ROOT (the checkout), WORK (the stage's directory under
# target/), VM_STAGE (its name in messages) and VM_STAGE_WHAT (what must run, e.g. "the
# vcan tests"), and defines run_vm (the boot phase) before vm_boot_only or vm_prepared
# is called; VM_SKIP_HINT, if set, is said after a skip.

# The build the VMs run: debug by default, the one `cargo test --workspace --all-targets`
# made just before in ./test.sh, so no stage builds again. An optimised build of the
# workspace costs CI's two cores 12 minutes and more; the checks pass on either (the
# systemd checks take about 4 minutes longer on debug binaries under emulation).
# VM_PROFILE=release runs them on the release build (the CAN benchmark figures in
# docs/guide/can.md are from it).
VM_PROFILE=${VM_PROFILE:-debug}
case $VM_PROFILE in
debug) VM_CARGO_PROFILE=() ;;
release) VM_CARGO_PROFILE=(--release) ;;
*) echo "VM_PROFILE must be debug or release, not '$VM_PROFILE'" >&2; exit 2 ;;
esac
# Where that build's binaries are, relative to the checkout.
VM_BIN_DIR=target/$VM_PROFILE

# A stage runs in two phases, chosen by its first argument (none: both): `prepare`
# installs what it needs, builds, and packs what the VM takes (binaries copied out of
# target/); `boot` runs the VM on what prepare left and reports. ./test.sh prepares
# the stages one by one and boots them beside `cargo test` (which keeps less than one
# of the two cores busy): a boot runs no cargo and reads nothing of target/debug,
# whose binaries the tests are running.
case ${1:-} in
prepare | boot) VM_PHASE=$1 ;;
*) VM_PHASE=all ;;
esac
vm_prepares() { [[ $VM_PHASE != boot ]]; }
vm_boots() { [[ $VM_PHASE != prepare ]]; }
# Prepare's mark that it finished (one that skipped left none), under the stage's WORK.
VM_PREPARED=$WORK/prepared
if vm_prepares; then rm -f "$VM_PREPARED"; fi
# vm_boot_only: the `boot` phase: the stage's run_vm on what prepare left, then exit.
vm_boot_only() {
    [[ -e $VM_PREPARED ]] || skip_or_fail "nothing prepared (tests/$VM_STAGE/run.sh prepare did not finish)"
    run_vm
    exit
}
# vm_prepared: prepare's end: its mark, then run_vm unless only preparing.
vm_prepared() {
    touch "$VM_PREPARED"
    if vm_boots; then run_vm; fi
}
# The kernel and modules vm_kernel keeps.
KDIR=$ROOT/target/vm-kernel

# skip_or_fail MESSAGE: under CI a stage that cannot run fails; elsewhere it is skipped,
# saying so.
skip_or_fail() {
    if [[ -n "${CI:-}" ]]; then
        echo "$VM_STAGE: FAILED: $1 (CI is set: $VM_STAGE_WHAT must run)" >&2
        exit 1
    fi
    echo "$VM_STAGE: SKIPPED: $1" >&2
    [[ -z "${VM_SKIP_HINT:-}" ]] || echo "$VM_STAGE: $VM_SKIP_HINT" >&2
    exit 0
}

# vm_install LOG PACKAGE...: installs the packages with apt-get, its output in LOG (a
# path under the checkout); skip_or_fail when that fails.
vm_install() {
    local log=$1
    shift
    echo "$VM_STAGE: installing $*"
    mkdir -p "$(dirname "$log")"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"; } \
        >"$log" 2>&1 || skip_or_fail "could not install $* (see ${log#"$ROOT"/})"
}

# The modules the VMs load, as paths under the kernel package's lib/modules/*/kernel.
VM_MODULES=(
    # vcan: can-bcm because python-can sends the Python node's heartbeat through it.
    net/can/can.ko net/can/can-raw.ko net/can/can-bcm.ko
    drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko
    # systemd: the host's root over virtio 9p, under a tmpfs overlay.
    drivers/virtio/virtio.ko drivers/virtio/virtio_ring.ko
    drivers/virtio/virtio_pci_legacy_dev.ko drivers/virtio/virtio_pci_modern_dev.ko
    drivers/virtio/virtio_pci.ko fs/netfs/netfs.ko fs/fscache/fscache.ko
    drivers/char/virtio_console.ko
    net/9p/9pnet.ko net/9p/9pnet_virtio.ko fs/9p/9p.ko fs/overlayfs/overlay.ko
    # powerloss: ext4 on a virtio disk, besides the 9p root and its overlay.
    lib/crc16.ko crypto/crc32c_generic.ko lib/libcrc32c.ko fs/mbcache.ko
    fs/jbd2/jbd2.ko fs/ext4/ext4.ko drivers/block/virtio_blk.ko
)
# One list for every stage: a stage that found a module missing would empty the cache
# while a VM booted before it may still be reading its kernel.

# Fills KDIR with vmlinuz and mods/*.ko (every VM_MODULES entry), taken
# from Debian's current kernel package and cached under target/vm-kernel.
vm_kernel() {
    local m have=1
    [[ -f $KDIR/vmlinuz ]] || have=0
    for m in "${VM_MODULES[@]}"; do [[ -f $KDIR/mods/$(basename "$m") ]] || have=0; done
    ((have)) && return 0
    apt-get update -qq >/dev/null 2>&1 || true
    # The plain -amd64 flavour: -cloud-amd64 has no CAN modules.
    local kpkg
    kpkg=$(apt-cache depends linux-image-amd64 2>/dev/null | grep -o 'linux-image-[0-9][^ ]*-amd64' | head -1)
    [[ -n "$kpkg" ]] || skip_or_fail "no linux-image-*-amd64 package known to apt"
    rm -rf "$KDIR" && mkdir -p "$KDIR/mods" "$KDIR/x"
    (cd "$KDIR" && apt-get download "$kpkg" >/dev/null 2>&1) || skip_or_fail "cannot download $kpkg"
    dpkg -x "$KDIR"/linux-image-*.deb "$KDIR/x"
    for m in "${VM_MODULES[@]}"; do cp "$KDIR"/x/lib/modules/*/kernel/"$m" "$KDIR/mods/"; done
    cp "$KDIR"/x/boot/vmlinuz-* "$KDIR/vmlinuz"
    rm -rf "$KDIR/x" "$KDIR"/linux-image-*.deb
}

# vm_build LOG [CARGO_ARG...]: the workspace's test build, as ./test.sh's `cargo test`
# makes it (the same targets and so the same features: nothing is built twice), in
# VM_PROFILE; cargo's stdout on stdout, its stderr appended to LOG. Fails the stage with
# the end of LOG when the build fails.
vm_build() {
    local log=$1
    shift
    cargo test "${VM_CARGO_PROFILE[@]}" --workspace --all-targets --no-run --locked "$@" 2>>"$log" ||
        { tail -20 "$log" >&2; echo "$VM_STAGE: FAILED: build (${log#"$ROOT"/})" >&2; exit 1; }
}

# carry IR BINARY DEST: a program and its shared libraries into the initramfs tree IR.
carry() {
    local ir=$1 l
    cp -L "$2" "$ir$3"
    for l in $(ldd "$2" | grep -o '/[^ ]*'); do
        mkdir -p "$ir$(dirname "$l")"
        [[ -e "$ir$l" ]] || cp -L "$l" "$ir$l"
    done
}
