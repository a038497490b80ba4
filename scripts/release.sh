#!/usr/bin/env bash
# Builds klipcal's release assets for Moonraker's update_manager (type: executable): one bare
# binary per target, named as `klipcal install` writes `asset_name` in release_info.json
# (klipcal-x86_64-linux, klipcal-aarch64-linux, klipcal-armv7-linux), plus SHA256SUMS and the
# release_info.json of each (for reference: install writes it next to the binary).
#
#   scripts/release.sh [OUT_DIR]        (default dist/v<version>)
#
# Upload every file of OUT_DIR to a GitHub release whose name is the version (v0.1.0):
# Moonraker compares that name with release_info.json's version and downloads the asset named
# there. Targets whose Rust standard library (rustup target add …) or linker is missing are
# skipped and named.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

version="$(sed -n 's/^version = "\(.*\)"/\1/p' Cargo.toml | head -n 1)"
out="${1:-dist/v$version}"
owner_repo="${KLIPCAL_REPO:-klipcal/klipcal}"
mkdir -p "$out"

installed="$(rustup target list --installed 2>/dev/null || rustc -vV | sed -n 's/^host: //p')"
built=()
missing=()
# target triple | asset arch | linker the target needs (empty: the host's)
for spec in \
    "x86_64-unknown-linux-gnu|x86_64|" \
    "aarch64-unknown-linux-gnu|aarch64|aarch64-linux-gnu-gcc" \
    "armv7-unknown-linux-gnueabihf|armv7|arm-linux-gnueabihf-gcc"; do
    IFS='|' read -r triple arch linker <<<"$spec"
    if ! grep -qx "$triple" <<<"$installed"; then
        missing+=("$triple (rustup target add $triple)")
        continue
    fi
    if [[ -n "$linker" ]] && ! command -v "$linker" >/dev/null; then
        missing+=("$triple (linker $linker not installed)")
        continue
    fi
    env_name="CARGO_TARGET_$(tr 'a-z-' 'A-Z_' <<<"$triple")_LINKER"
    if [[ -n "$linker" ]]; then export "$env_name=$linker"; fi
    echo "release: building $triple"
    cargo build --release --locked --target "$triple" --quiet
    asset="klipcal-$arch-linux"
    cp "target/$triple/release/klipcal" "$out/$asset"
    chmod 755 "$out/$asset"
    owner="${owner_repo%%/*}"
    name="${owner_repo#*/}"
    printf '{\n  "project_name": "%s",\n  "project_owner": "%s",\n  "version": "v%s",\n  "asset_name": "%s"\n}\n' \
        "$name" "$owner" "$version" "$asset" >"$out/release_info-$arch.json"
    built+=("$asset")
done

if [[ ${#built[@]} -eq 0 ]]; then
    echo "release: nothing built; missing: ${missing[*]}" >&2
    exit 1
fi
(cd "$out" && sha256sum "${built[@]}" >SHA256SUMS)
echo "release: v$version in $out: ${built[*]}"
for m in "${missing[@]}"; do
    echo "release: skipped $m"
done
