#!/usr/bin/env bash
# Installs compgate as a systemd service on a shop-floor PC. Run as root from the
# repository after `cargo build --release`:
#
#   sudo deploy/install.sh [CONFIG.toml]
#
# - binary       -> /usr/local/bin/compgate
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
binary=target/release/compgate
if [[ ! -x $binary ]]; then
    echo "install.sh: $binary missing; run 'cargo build --release' first" >&2
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
install -m 0644 deploy/compgate.service /etc/systemd/system/compgate.service

/usr/local/bin/compgate validate --config /etc/compgate/compgate.toml
systemctl daemon-reload
systemctl enable --now compgate.service
systemctl --no-pager status compgate.service || true
echo "logs: journalctl -u compgate -f    reload config: systemctl reload compgate"
