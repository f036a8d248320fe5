#!/usr/bin/env bash
# Builds the production binary and installs compgate as a systemd service on a
# shop-floor PC, or updates an installed one. Run as root from the repository:
#
#   sudo deploy/install.sh [--replace-config] [CONFIG.toml]
#
# To update, run it without CONFIG.toml: the installed config stays.
# - binary       -> /usr/local/bin/compgate, built without the default `sim` feature:
#                   no simulated plant (demo, sim, scenario, backlash --sim) in it; a
#                   different one installed before is kept as compgate.prev
# - manual       -> /usr/local/share/doc/compgate (README.md and docs/)
# - config       -> /etc/compgate/compgate.toml: CONFIG.toml when given (a relative
#                   path is taken from where the script is run); without it the
#                   installed config stays, or config/example.toml on a first install.
#                   An installed config that differs from CONFIG.toml is replaced only
#                   with --replace-config (and kept as compgate.toml.<date-time>);
#                   without it the script shows the difference and stops before it
#                   installs anything.
# - unit         -> /etc/systemd/system/compgate.service; an installed one that differs
#                   (an earlier version's, or edited with `systemctl edit --full`) is
#                   kept as /etc/compgate/compgate.service.<date-time>. Drop-ins
#                   (`systemctl edit compgate`) are not touched.
# - system user  compgate (no login, no home), member of dialout for RS-485 adapters
# - state        /var/lib/compgate (systemd's StateDirectory: the recorder's database)
# The config that will run is validated by the new binary, as the user compgate and
# with the unit's STATE_DIRECTORY, before anything is installed; then the service is
# enabled and (re)started, so an update runs the new binary and config at once. If it
# does not start, the script prints the commands that go back to what ran before.
set -euo pipefail

if [[ $(id -u) -ne 0 ]]; then
    echo "install.sh: run as root" >&2
    exit 1
fi
usage="usage: install.sh [--replace-config] [CONFIG.toml]"
replace_config=no
given=()
for arg in "$@"; do
    if [[ $arg == --replace-config ]]; then
        replace_config=yes
    elif [[ $arg == -* || ${#given[@]} -gt 0 ]]; then
        echo "$usage" >&2
        exit 2
    else
        given=("$arg")
    fi
done
if [[ $replace_config == yes && ${#given[@]} -eq 0 ]]; then
    echo "install.sh: --replace-config needs the CONFIG.toml that replaces the installed one" >&2
    echo "$usage" >&2
    exit 2
fi
config=/etc/compgate/compgate.toml
state=/var/lib/compgate
stamp=$(date +%Y%m%d-%H%M%S)
if [[ ${#given[@]} -eq 1 ]]; then
    # From where the script was run: before the cd into the repository below.
    if ! config_src=$(realpath -e -- "${given[0]}" 2>/dev/null) || [[ ! -f $config_src ]]; then
        echo "install.sh: ${given[0]}: no such file (run in $PWD)" >&2
        exit 1
    fi
    echo "install.sh: config $config_src"
    # An installed config that differs may hold what was tuned on this machine since.
    if [[ $replace_config == no && -e $config && $config_src != "$config" ]] &&
        ! cmp -s "$config_src" "$config"; then
        difference=$(diff -u "$config" "$config_src" || true)
        lines=$(wc -l <<<"$difference")
        {
            echo "install.sh: the installed $config differs from $config_src:"
            head -n 60 <<<"$difference"
            ((lines <= 60)) || echo "... $((lines - 60)) more lines: diff -u $config $config_src"
            echo "install.sh: nothing installed. Either update and keep the installed config:"
            echo "    $0"
            echo "or install $config_src in its place (the installed one kept as $config.<date-time>):"
            echo "    $0 --replace-config $config_src"
        } >&2
        exit 1
    fi
fi
cd "$(dirname "$0")/.."

if [[ ${#given[@]} -eq 0 && -e $config ]]; then
    config_src=$config
elif [[ ${#given[@]} -eq 0 ]]; then
    config_src=config/example.toml
fi
# Its own target directory, so the demo build in target/release stays as it is.
build=(cargo build --release --locked --no-default-features --bin compgate
    --target-dir target/production)
binary=target/production/release/compgate
if command -v cargo >/dev/null 2>&1; then
    "${build[@]}"
elif [[ -n ${SUDO_USER:-} ]] && sudo -u "$SUDO_USER" bash -lc 'command -v cargo' >/dev/null 2>&1; then
    # rustup installs cargo per user: build as the user who called sudo.
    sudo -u "$SUDO_USER" bash -lc "cd '$PWD' && ${build[*]}"
elif [[ -x $binary ]]; then
    # A PC without Rust: the binary built on another machine and copied here.
    echo "install.sh: cargo not found; installing $binary as built before ($(date -r "$binary" '+%Y-%m-%d %H:%M'))"
else
    echo "install.sh: cargo not found and no $binary: run '${build[*]}' (here or on a machine with Rust, then copy the binary there) and then this script" >&2
    exit 1
fi
if [[ ! -x $binary ]]; then
    echo "install.sh: $binary missing" >&2
    exit 1
fi
# A binary copied from another machine may be built for another CPU (an aarch64 build
# on a 32-bit ARM userland, an x86 one on an ARM box): the kernel would not run it,
# and the validate below would blame the config.
if ! "$binary" --version >/dev/null 2>&1; then
    # The ELF header's e_machine (bytes 18-19, little endian), as `uname -m` names it.
    case $(od -An -tx1 -j18 -N2 "$binary" 2>/dev/null | tr -d ' \n') in
    3e00) built_for=x86_64 ;; b700) built_for=aarch64 ;; 2800) built_for="32-bit ARM" ;;
    0300) built_for="32-bit x86" ;; *) built_for="an unknown machine" ;;
    esac
    echo "install.sh: $binary does not run on this machine ($(uname -m)); it is built for $built_for: build it here, or for $(uname -m) (docs/deployment.md, ARM boxes), nothing installed" >&2
    exit 1
fi

if ! id compgate >/dev/null 2>&1; then
    useradd --system --no-create-home --home-dir "$state" \
        --shell /usr/sbin/nologin --user-group compgate
fi
getent group dialout >/dev/null && usermod -a -G dialout compgate

# validate checks that the recorder can write its database: the state directory as
# the unit's StateDirectory= makes it, and a relative recorder.path taken from it. It
# warns when the database is outside it: the unit's sandbox would not let it write
# there (or, in /tmp, would keep it private and drop it at every stop). It runs as the
# service does, as the user compgate (a database root made by hand fails here, not at
# the restart), on copies that user can read (the repository or CONFIG.toml may be in a
# home directory closed to it); its messages name CONFIG.toml, not the copy.
install -d -m 0750 -o compgate -g compgate "$state"
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
install -m 0755 "$binary" "$stage/compgate"
install -m 0640 -g compgate "$config_src" "$stage/compgate.toml"
chgrp compgate "$stage" && chmod 0750 "$stage"
validated=yes
report=$(setpriv --reuid=compgate --regid=compgate --init-groups \
    env -C "$state" STATE_DIRECTORY="$state" \
    "$stage/compgate" validate --config "$stage/compgate.toml" 2>&1) || validated=no
echo "${report//"$stage/compgate.toml"/"$config_src"}"
if [[ $validated == no ]]; then
    echo "install.sh: as the user compgate, $config_src does not validate: nothing installed, the service is as it was" >&2
    exit 1
fi

bin=/usr/local/bin/compgate
back=() # the commands that go back to what ran before, should the service not start
if [[ -e $bin ]] && ! cmp -s "$stage/compgate" "$bin"; then
    cp -p "$bin" "$bin.prev"
    echo "kept the previous binary as $bin.prev"
    back+=("cp -p $bin.prev $bin")
fi
install -m 0755 "$stage/compgate" "$bin"
echo "installed $("$bin" --version) as $bin"
install -d -m 0750 -o root -g compgate /etc/compgate
if [[ $config_src == "$config" ]]; then
    echo "kept the installed $config"
elif [[ ! -e $config ]]; then
    install -m 0640 -o root -g compgate "$config_src" "$config"
    echo "installed $config_src as $config: edit it for this machine"
elif cmp -s "$config_src" "$config"; then
    echo "$config is already $config_src: unchanged"
else
    # Only with --replace-config (checked above).
    backup=$config.$stamp
    cp -p "$config" "$backup"
    install -m 0640 -o root -g compgate "$config_src" "$config"
    echo "replaced $config with $config_src; the previous one is $backup"
    back+=("cp -p $backup $config")
fi
install -d -m 0755 /usr/local/share/doc/compgate
install -m 0644 README.md /usr/local/share/doc/compgate/README.md
cp -r docs /usr/local/share/doc/compgate/
unit=/etc/systemd/system/compgate.service
if [[ -e $unit ]] && ! cmp -s deploy/compgate.service "$unit"; then
    # Not beside it: /etc/systemd/system is systemd's to read.
    unit_backup=/etc/compgate/compgate.service.$stamp
    cp -p "$unit" "$unit_backup"
    echo "the installed $unit differed from deploy/compgate.service (an earlier version's, or edited with systemctl edit --full): kept as $unit_backup; changes of this machine's own belong in a drop-in (systemctl edit compgate), which updates keep"
    back+=("cp -p $unit_backup $unit && systemctl daemon-reload")
fi
install -m 0644 deploy/compgate.service "$unit"

# Enabled before the one reload: `enable` alone reloads systemd as well, and a reload
# re-reads every unit and re-runs every generator (seconds on a slow box).
systemctl enable --no-reload compgate.service
systemctl daemon-reload
# A running service keeps its old binary and config until restarted.
if systemctl is-active --quiet compgate.service; then
    echo "compgate was running: restarting it on the new binary and config"
else
    echo "starting compgate"
fi
if ! systemctl restart compgate.service; then
    systemctl --no-pager status compgate.service || true
    echo "install.sh: compgate did not start: journalctl -u compgate -e" >&2
    if [[ ${#back[@]} -gt 0 ]]; then
        echo "install.sh: to go back to what ran before:" >&2
        printf '    %s\n' "${back[@]}" "systemctl restart compgate" >&2
    fi
    exit 1
fi
systemctl --no-pager status compgate.service || true
echo "logs: journalctl -u compgate -f    reload config: systemctl reload compgate"
