#!/usr/bin/env bash
# Builds the production binary and installs compgate as a systemd service on a
# shop-floor PC. Run as root from the repository:
#
#   sudo deploy/install.sh [CONFIG.toml]
#
# - binary       -> /usr/local/bin/compgate, built without the default `sim` feature:
#                   no simulated plant (demo, sim, scenario, backlash --sim) in it
# - manual       -> /usr/local/share/doc/compgate (README.md and docs/)
# - config       -> /etc/compgate/compgate.toml (only if absent; default: config/example.toml)
# - unit         -> /etc/systemd/system/compgate.service
# - system user  compgate (no login, no home), member of dialout for RS-485 adapters
# - state        /var/lib/compgate (systemd's StateDirectory: the recorder's database)
# The config is validated before the service is enabled and started.
set -euo pipefail
cd "$(dirname "$0")/.."

if [[ $(id -u) -ne 0 ]]; then
    echo "install.sh: run as root" >&2
    exit 1
fi
config_src=${1:-config/example.toml}
# Its own target directory, so the demo build in target/release stays as it is.
build=(cargo build --release --locked --no-default-features --bin compgate
    --target-dir target/production)
binary=target/production/release/compgate
if command -v cargo >/dev/null 2>&1; then
    "${build[@]}"
elif [[ -n ${SUDO_USER:-} ]]; then
    # rustup installs cargo per user: build as the user who called sudo.
    sudo -u "$SUDO_USER" bash -lc "cd '$PWD' && ${build[*]}"
else
    echo "install.sh: cargo not found; run '${build[*]}' and then this script" >&2
fi
if [[ ! -x $binary ]]; then
    echo "install.sh: $binary missing" >&2
    exit 1
fi

if ! id compgate >/dev/null 2>&1; then
    useradd --system --no-create-home --home-dir /var/lib/compgate \
        --shell /usr/sbin/nologin --user-group compgate
fi
getent group dialout >/dev/null && usermod -a -G dialout compgate

install -m 0755 "$binary" /usr/local/bin/compgate
install -d -m 0750 -o root -g compgate /etc/compgate
if [[ ! -e /etc/compgate/compgate.toml ]]; then
    install -m 0640 -o root -g compgate "$config_src" /etc/compgate/compgate.toml
    echo "installed $config_src as /etc/compgate/compgate.toml: edit it for this machine"
fi
install -d -m 0755 /usr/local/share/doc/compgate
install -m 0644 README.md /usr/local/share/doc/compgate/README.md
cp -r docs /usr/local/share/doc/compgate/
install -m 0644 deploy/compgate.service /etc/systemd/system/compgate.service

# validate checks that the recorder can write its database: the state directory as
# the unit's StateDirectory= makes it, and a relative recorder.path taken from it.
install -d -m 0750 -o compgate -g compgate /var/lib/compgate
STATE_DIRECTORY=/var/lib/compgate /usr/local/bin/compgate validate --config /etc/compgate/compgate.toml
systemctl daemon-reload
systemctl enable --now compgate.service
systemctl --no-pager status compgate.service || true
echo "logs: journalctl -u compgate -f    reload config: systemctl reload compgate"
