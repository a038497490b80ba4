#!/usr/bin/env bash
# The one command that runs every test of klipcal on a fresh machine:
#   1. installs what the tests need (Debian's libusb-dev when missing, the bench's Python venvs
#      with Moonraker and Klipper's host from PyPI, cached under .bench/),
#   2. builds the workspace (the pure core, the daemon, the benchmarks) and runs `cargo test` for
#      everything: unit tests, the integration tests that start the bench (a real Moonraker + a
#      real klippy on loopback) and the daemon,
#   3. runs the documentation examples (`cargo test --doc`; `--all-targets` skips them),
#   4. runs the cross test (tests/cross/run.sh): the aarch64 and armv7 builds under qemu-user
#      beside the x86_64 one, installing Debian's cross toolchain and qemu when missing.
# A bench that cannot start fails the tests; nothing is skipped silently.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

if ! command -v cargo >/dev/null; then
    echo "run-all: cargo not found; install the Rust toolchain (rustup) first" >&2
    exit 1
fi

echo "== bench setup"
bash tests/bench/setup.sh

echo "== cargo fmt --check, cargo clippy"
# The code's shape is part of the tests: formatted, and no clippy warning.
cargo fmt --all --check
cargo clippy --workspace --all-targets --quiet -- -D warnings
# The printer's build (scripts/release.sh: the daemon alone, no simulator) too.
cargo clippy -p klipcal --lib --bins --quiet -- -D warnings

echo "== cargo test"
# Each integration test starts its own bench on free ports; four at a time fit two cores.
cargo test --workspace --all-targets -- --test-threads="${KLIPCAL_TEST_THREADS:-4}"

echo "== cargo test --doc"
cargo test --workspace --doc

echo "== cross (aarch64, armv7 under qemu-user)"
# KLIPCAL_CROSS_TEST: a stand-in for tests/it/runall.rs only.
"${KLIPCAL_CROSS_TEST:-tests/cross/run.sh}"
