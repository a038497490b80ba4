#!/usr/bin/env bash
# Builds klipcal's release assets for Moonraker's update_manager (type: executable) on a Debian
# amd64 machine: one bare binary per target, named as `klipcal install` writes `asset_name` in
# release_info.json, plus the release_info.json of each asset and SHA256SUMS:
#
#   klipcal-x86_64-linux   klipcal-aarch64-linux   klipcal-armv7-linux
#   release_info-x86_64.json   release_info-aarch64.json   release_info-armv7.json   SHA256SUMS
#
#   scripts/release.sh [OUT_DIR]        (default dist/v<version>)
#   KLIPCAL_REPO=owner/name             the GitHub repository the release goes to
#                                       (default klipcal/klipcal, as `klipcal install --repo`)
#   KLIPCAL_RELEASE_PROFILE=NAME        cargo profile (default release)
#
# It installs what it needs itself with apt-get (scripts/cross-toolchain.sh: Debian's
# rustc-web/cargo-web, the arm64/armhf standard library of that compiler, the cross gccs and
# their C libraries); all three targets are built by that one compiler. x86_64 and aarch64 are
# required: it fails when either cannot be built. armv7 is built when its standard library can
# be had, and otherwise reported missing with the reason (exit status 0, the reason printed).
#
# Upload every file of OUT_DIR to the GitHub release of KLIPCAL_REPO whose name is the version
# (v0.1.0): Moonraker compares that name with release_info.json's version and downloads the
# asset named there. Each build's time and peak memory (the largest single compiler process)
# are printed, and written to OUT_DIR/build-stats.txt (not an asset).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
. scripts/cross-toolchain.sh

version="$(sed -n 's/^version = "\(.*\)"/\1/p' Cargo.toml | head -n 1)"
out="${1:-dist/v$version}"
owner_repo="${KLIPCAL_REPO:-klipcal/klipcal}"
profile="${KLIPCAL_RELEASE_PROFILE:-release}"
if [[ "$owner_repo" != */* ]]; then
    echo "release: KLIPCAL_REPO=$owner_repo: expected owner/name" >&2
    exit 1
fi
owner="${owner_repo%%/*}"
name="${owner_repo#*/}"

if ! cross_toolchain_setup; then
    printf 'release: cannot build: %s\n' "${CROSS_MISSING[@]}" >&2
    exit 1
fi
mkdir -p "$out"
: >"$out/build-stats.txt"
built=()
failed=()
for triple in "${CROSS_TRIPLES[@]}"; do
    arch="$(cross_arch "$triple")"
    if ! printf '%s\n' "${CROSS_OK[@]}" | grep -qx "$triple"; then
        continue
    fi
    echo "release: building $triple (profile $profile, Debian rustc $CROSS_RUSTC_VERSION)"
    stats="$(mktemp)"
    if ! bin="$(CROSS_TIME_FILE="$stats" cross_build "$triple" "$profile")"; then
        failed+=("$triple: cargo build failed (see above)")
        rm -f "$stats"
        continue
    fi
    read -r wall user sys maxkb <"$stats"
    rm -f "$stats"
    asset="klipcal-$arch-linux"
    cp "$bin" "$out/$asset"
    chmod 755 "$out/$asset"
    printf '{\n  "project_name": "%s",\n  "project_owner": "%s",\n  "version": "v%s",\n  "asset_name": "%s"\n}\n' \
        "$name" "$owner" "$version" "$asset" >"$out/release_info-$arch.json"
    size="$(stat -c %s "$out/$asset")"
    line="$(awk -v a="$asset" -v s="$size" -v w="$wall" -v u="$user" -v y="$sys" -v m="$maxkb" \
        'BEGIN { printf "%-24s %6.2f MB   build %4.0f s wall, %5.0f s CPU, peak %5.0f MB (largest single process)", a, s / 1e6, w, u + y, m / 1024 }')"
    echo "release: $line"
    echo "$line" >>"$out/build-stats.txt"
    built+=("$asset")
done

(cd "$out" && sha256sum "${built[@]}" >SHA256SUMS)
echo "release: v$version for $owner_repo in $out: ${built[*]}"
status=0
for m in "${CROSS_MISSING[@]}" "${failed[@]}"; do
    [[ -n "$m" ]] || continue
    echo "release: MISSING $m" >&2
    case "$m" in armv7-*) ;; *) status=1 ;; esac
done
for need in klipcal-x86_64-linux klipcal-aarch64-linux; do
    [[ -f "$out/$need" ]] || status=1
done
exit "$status"
