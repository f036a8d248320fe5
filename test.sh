#!/usr/bin/env bash
# Runs every test of compgate: formatting, lints, unit, integration and doc tests of
# the whole workspace. Installs what it needs first. CI runs exactly this (.ci/run).
set -euo pipefail
cd "$(dirname "$0")"

# Rust components the checks use (present on a standard rustup toolchain).
rustup component add rustfmt clippy >/dev/null 2>&1 || true

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets -- -D warnings
echo "== cargo test"
cargo test --workspace --all-targets
cargo test --workspace --doc
echo "== vcan tests (CAN source and CANopen node; natively on vcan0, else in a VM)"
tests/vcan/run.sh
