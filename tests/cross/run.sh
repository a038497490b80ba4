#!/usr/bin/env bash
# The cross test (called by tests/run-all.sh): klipcal built for aarch64 and armv7 with
# Debian's cross toolchain (scripts/cross-toolchain.sh, installed here with apt-get when
# missing) and run under qemu-user beside the x86_64 binary `cargo test` uses:
#   --version; the offline commands on the same inputs with identical output; on the bench
#   (real Moonraker + klippy) the daemon registering and answering KLIPCAL_STATUS run through
#   Klipper, `install --dry-run`, and a real `install` from the aarch64 binary that Moonraker's
#   update manager accepts (tests/cross/check.py says what each check asserts).
# Build profile: cargo profile `cross-test` (Cargo.toml), target dir target/cross.
# Fails, saying why, when qemu or the cross toolchain cannot be installed, or aarch64 cannot be
# built. armv7 is built when a standard library of the compiler's version can be had for it;
# otherwise it is reported MISSING with the reason, and the rest must pass.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
. scripts/cross-toolchain.sh

t0=$(date +%s)
say() { echo "cross: $*"; }
fail() {
    echo "cross: FAILED: $*" >&2
    exit 1
}

bash tests/bench/setup.sh >/dev/null
if ! cross_toolchain_setup --with-qemu; then
    fail "$(printf '%s; ' "${CROSS_MISSING[@]}")(apt log: $CROSS_LOG)"
fi
has() { printf '%s\n' "${CROSS_OK[@]}" | grep -qx "$1"; }
has aarch64-unknown-linux-gnu || fail "$(printf '%s; ' "${CROSS_MISSING[@]}")"
t_setup=$(($(date +%s) - t0))

# The reference: the x86_64 binary the rest of the tests run (no-op after `cargo test`).
cargo build --quiet --bin klipcal
# Outside the repository: Moonraker refuses an update_manager path inside a git repository.
work="$(mktemp -d /tmp/klipcal-cross.XXXXXX)"
args=(--ref target/debug/klipcal --work "$work" --install-arch aarch64)
builds=""
for triple in aarch64-unknown-linux-gnu armv7-unknown-linux-gnueabihf; do
    has "$triple" || continue
    arch="$(cross_arch "$triple")"
    tb=$(date +%s)
    bin="$(cross_build "$triple" cross-test)" || fail "cargo build --target $triple failed"
    builds+=" $arch $(($(date +%s) - tb)) s,"
    args+=(--bin "$arch=$bin")
done
t_build=$(($(date +%s) - t0 - t_setup))
say "built:${builds%,} (toolchain setup ${t_setup} s)"

status=0
if python3 tests/cross/check.py "${args[@]}"; then
    rm -rf "$work"
else
    status=1
    say "kept $work (bench logs, outputs)"
fi
for m in "${CROSS_MISSING[@]}"; do
    say "MISSING $m"
done
say "took $(($(date +%s) - t0)) s: setup ${t_setup} s, builds ${t_build} s, checks $(($(date +%s) - t0 - t_setup - t_build)) s"
exit "$status"
