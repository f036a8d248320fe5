#!/usr/bin/env bash
# Builds the production binary and installs compgate as a systemd service on a
# shop-floor PC, or updates an installed one. Run as root from the repository:
#
#   sudo deploy/install.sh [CONFIG.toml]
#
# - binary       -> /usr/local/bin/compgate, built without the default `sim` feature:
#                   no simulated plant (demo, sim, scenario, backlash --sim) in it
# - manual       -> /usr/local/share/doc/compgate (README.md and docs/)
# - config       -> /etc/compgate/compgate.toml: CONFIG.toml when given (an installed
#                   config that differs is kept as compgate.toml.<date-time>); without
#                   it the installed config stays, or config/example.toml on a first
#                   install
# - unit         -> /etc/systemd/system/compgate.service
# - system user  compgate (no login, no home), member of dialout for RS-485 adapters
# - state        /var/lib/compgate (systemd's StateDirectory: the recorder's database)
# The config that will run is validated by the new binary before anything is
# installed; then the service is enabled and (re)started, so an update runs the new
# binary and config at once.
set -euo pipefail
cd "$(dirname "$0")/.."

if [[ $(id -u) -ne 0 ]]; then
    echo "install.sh: run as root" >&2
    exit 1
fi
if [[ $# -gt 1 || ${1:-} == -* ]]; then
    echo "usage: install.sh [CONFIG.toml]" >&2
    exit 2
fi
config=/etc/compgate/compgate.toml
state=/var/lib/compgate
if [[ $# -eq 1 ]]; then
    config_src=$1
    if [[ ! -f $config_src ]]; then
        echo "install.sh: $config_src: no such file" >&2
        exit 1
    fi
elif [[ -e $config ]]; then
    config_src=$config
else
    config_src=config/example.toml
fi
# Its own target directory, so the demo build in target/release stays as it is.
build=(cargo build --release --locked --no-default-features --bin compgate
    --target-dir target/production)
binary=target/production/release/compgate
if command -v cargo >/dev/null 2>&1; then
    "${build[@]}"
elif [[ -n ${SUDO_USER:-} ]]; then
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

if ! id compgate >/dev/null 2>&1; then
    useradd --system --no-create-home --home-dir "$state" \
        --shell /usr/sbin/nologin --user-group compgate
fi
getent group dialout >/dev/null && usermod -a -G dialout compgate

# validate checks that the recorder can write its database: the state directory as
# the unit's StateDirectory= makes it, and a relative recorder.path taken from it. It
# warns when the database is outside it: the unit's sandbox would not let it write
# there (or, in /tmp, would keep it private and drop it at every stop).
install -d -m 0750 -o compgate -g compgate "$state"
if ! STATE_DIRECTORY=$state "$binary" validate --config "$config_src"; then
    echo "install.sh: $config_src does not validate: nothing installed, the service is as it was" >&2
    exit 1
fi

install -m 0755 "$binary" /usr/local/bin/compgate
install -d -m 0750 -o root -g compgate /etc/compgate
if [[ $config_src == "$config" ]]; then
    echo "kept the installed $config"
elif [[ ! -e $config ]]; then
    install -m 0640 -o root -g compgate "$config_src" "$config"
    echo "installed $config_src as $config: edit it for this machine"
elif cmp -s "$config_src" "$config"; then
    echo "$config is already $config_src: unchanged"
else
    backup=$config.$(date +%Y%m%d-%H%M%S)
    cp -p "$config" "$backup"
    install -m 0640 -o root -g compgate "$config_src" "$config"
    echo "replaced $config with $config_src; the previous one is $backup"
fi
install -d -m 0755 /usr/local/share/doc/compgate
install -m 0644 README.md /usr/local/share/doc/compgate/README.md
cp -r docs /usr/local/share/doc/compgate/
install -m 0644 deploy/compgate.service /etc/systemd/system/compgate.service

systemctl daemon-reload
systemctl enable compgate.service
# A running service keeps its old binary and config until restarted.
if systemctl is-active --quiet compgate.service; then
    echo "compgate was running: restarting it on the new binary and config"
else
    echo "starting compgate"
fi
if ! systemctl restart compgate.service; then
    systemctl --no-pager status compgate.service || true
    echo "install.sh: compgate did not start: journalctl -u compgate -e" >&2
    exit 1
fi
systemctl --no-pager status compgate.service || true
echo "logs: journalctl -u compgate -f    reload config: systemctl reload compgate"
