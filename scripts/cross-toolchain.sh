# Sourced by scripts/release.sh and tests/cross/run.sh: brings Debian's cross toolchain for
# klipcal's three release targets onto this (Debian amd64) machine with apt-get, and says for
# each target whether it can be built and, when not, why.
#
#   . scripts/cross-toolchain.sh
#   cross_toolchain_setup [--with-qemu]     # returns 1 when nothing but x86_64 could be had
#   cross_build TRIPLE PROFILE              # after setup; prints the binary's path
#
# Rust: Debian's rustc-web/cargo-web (/usr/bin/rustc, /usr/bin/cargo), not rustup's toolchain,
# because rustup targets cannot be downloaded here while Debian ships the standard library of
# that very compiler for arm64 and armhf (libstd-rust-web-dev:arm64/:armhf). A standard library
# must come from the same compiler version: both versions are checked.
# armv7: when libstd-rust-web-dev:armhf of the compiler's version cannot be had (e.g. the
# armhf package index fails to download), std is compiled for armv7 from Debian's
# rust-web-src of the same version (cargo -Zbuild-std, allowed by RUSTC_BOOTSTRAP=1 for that
# one build). If that cannot be had either, armv7 is reported missing with the reason.
# C: bundled SQLite (rusqlite "bundled") is compiled by the cross gcc (CC_<triple>), against
# the cross sysroots of libc6-dev-arm64-cross / libc6-dev-armhf-cross, which also serve qemu
# (-L /usr/aarch64-linux-gnu, /usr/arm-linux-gnueabihf) to run the results.
#
# After setup: CROSS_OK (triples that can be built), CROSS_MISSING (lines "triple: reason"),
# CROSS_RUSTC_VERSION, and per triple CROSS_QEMU_<arch> for running its binaries.

CROSS_TRIPLES=(x86_64-unknown-linux-gnu aarch64-unknown-linux-gnu armv7-unknown-linux-gnueabihf)
CROSS_TARGET_DIR="${CROSS_TARGET_DIR:-target/cross}"
CROSS_OK=()
CROSS_MISSING=()
CROSS_ARMV7_BUILD_STD=0
CROSS_LOG="${CROSS_LOG:-/tmp/klipcal-cross-apt.log}"

_cross_say() { echo "cross: $*" >&2; }

# The asset arch of a triple, as `klipcal install` names the asset (klipcal-<arch>-linux).
cross_arch() {
    case "$1" in
        x86_64-*) echo x86_64 ;;
        aarch64-*) echo aarch64 ;;
        armv7-*) echo armv7 ;;
        *) return 1 ;;
    esac
}

# Debian architecture, gcc prefix and qemu of a triple.
_cross_deb_arch() { case "$1" in aarch64-*) echo arm64 ;; armv7-*) echo armhf ;; *) echo amd64 ;; esac; }
_cross_gnu() { case "$1" in aarch64-*) echo aarch64-linux-gnu ;; armv7-*) echo arm-linux-gnueabihf ;; *) echo x86_64-linux-gnu ;; esac; }
cross_qemu() {
    case "$1" in
        aarch64-*) echo "qemu-aarch64-static -L /usr/aarch64-linux-gnu" ;;
        armv7-*) echo "qemu-arm-static -L /usr/arm-linux-gnueabihf" ;;
        *) echo "" ;;
    esac
}

# apt-get/dpkg as root (sudo when not root).
_cross_root() {
    if [[ $(id -u) -eq 0 ]]; then
        "$@"
    elif command -v sudo >/dev/null; then
        sudo "$@"
    else
        _cross_say "needs root (or sudo): $*"
        return 1
    fi
}
_cross_apt() { _cross_root env DEBIAN_FRONTEND=noninteractive apt-get "$@" >>"$CROSS_LOG" 2>&1; }

# The installed version of a package ("" when not installed).
_cross_installed() { dpkg-query -W -f='${db:Status-Abbrev}|${Version}' "$1" 2>/dev/null | sed -n 's/^ii *|//p'; }
# The candidate version apt would install ("" or "(none)" when there is none).
_cross_candidate() { apt-cache policy "$1" 2>/dev/null | sed -n 's/^ *Candidate: //p'; }

# apt-get install, running apt-get update first when a package is unknown or stale.
_cross_install() {
    local missing=()
    for p in "$@"; do
        [[ -n "$(_cross_installed "$p")" ]] || missing+=("$p")
    done
    [[ ${#missing[@]} -eq 0 ]] && return 0
    _cross_say "apt-get install ${missing[*]}"
    _cross_apt install -y --no-install-recommends "${missing[@]}" && return 0
    _cross_apt update || true
    _cross_apt install -y --no-install-recommends "${missing[@]}"
}

# Adds a foreign dpkg architecture, updates apt's lists and tries to install the standard
# library of the compiler's version for it. Sets _cross_reason when it cannot.
_cross_foreign_std() {
    local deb_arch="$1" want="$2" pkg="libstd-rust-web-dev:$1" added=0 cand have errs
    _cross_reason=""
    have="$(_cross_installed "$pkg")"
    [[ "$have" == "$want" ]] && return 0
    if ! dpkg --print-foreign-architectures | grep -qx "$deb_arch"; then
        _cross_root dpkg --add-architecture "$deb_arch" || return 1
        added=1
    fi
    errs="$(_cross_root apt-get update 2>&1 | tee -a "$CROSS_LOG" | grep -E '^E:' | head -n 2 || true)"
    cand="$(_cross_candidate "$pkg")"
    if [[ "$cand" == "$want" ]]; then
        _cross_say "apt-get install $pkg=$want"
        if _cross_apt install -y --no-install-recommends "$pkg=$want" &&
            [[ "$(_cross_installed "$pkg")" == "$want" ]]; then
            return 0
        fi
        errs+=" $(grep -E '^E:' "$CROSS_LOG" | tail -n 2)"
    fi
    _cross_reason="$pkg $want cannot be had (apt's candidate: ${cand:-none}${have:+, installed: $have})"
    [[ -n "$errs" ]] && _cross_reason+="; apt-get update: $(tr '\n' ' ' <<<"$errs")"
    # An architecture this script added and could not use comes off again, so that a later
    # `apt-get update` (other scripts') does not fail on its index.
    if [[ $added -eq 1 ]] && [[ -z "$(dpkg-query -W -f='${Package}:${Architecture}\n' 2>/dev/null | grep ":$deb_arch\$")" ]]; then
        _cross_root dpkg --remove-architecture "$deb_arch" && _cross_apt update || true
    fi
    return 1
}

# Debian's compiler at the version apt has now, after `apt-get update`: the foreign
# architectures' libstd-rust-web-dev comes from the fresh lists, and must equal the compiler's
# version. A machine whose lists were older installed an older rustc-web than the std apt then
# offers (a fresh CI machine: rustc-web 1.85 from its image's lists, libstd 1.96 after the
# update), and every cross target went missing.
_cross_rustc_current() {
    local have cand
    _cross_apt update || true
    have="$(_cross_installed rustc-web)"
    cand="$(_cross_candidate rustc-web)"
    [[ -z "$cand" || "$cand" == "(none)" || "$cand" == "$have" ]] && return 0
    [[ "$(_cross_candidate cargo-web)" == "$cand" ]] || return 0
    _cross_say "apt-get install rustc-web=$cand cargo-web=$cand (was $have)"
    _cross_apt install -y --no-install-recommends "rustc-web=$cand" "cargo-web=$cand" || true
}

cross_toolchain_setup() {
    local with_qemu=0
    [[ "${1:-}" == "--with-qemu" ]] && with_qemu=1
    : >"$CROSS_LOG"
    if ! command -v apt-get >/dev/null || ! command -v dpkg >/dev/null; then
        CROSS_MISSING+=("all targets: not a Debian machine (no apt-get/dpkg); the cross toolchain comes from Debian's packages")
        return 1
    fi
    local base=(rustc-web cargo-web gcc-aarch64-linux-gnu gcc-arm-linux-gnueabihf
        libc6-dev-arm64-cross libc6-dev-armhf-cross)
    [[ $with_qemu -eq 1 ]] && base+=(qemu-user-static)
    if ! _cross_install "${base[@]}"; then
        CROSS_MISSING+=("all targets: apt-get install ${base[*]} failed: $(grep -E '^(E|Err):' "$CROSS_LOG" | tail -n 3 | tr '\n' ' ') (log: $CROSS_LOG)")
        return 1
    fi
    _cross_rustc_current
    CROSS_RUSTC_VERSION="$(_cross_installed rustc-web)"
    local rv
    rv="$(/usr/bin/rustc --version 2>&1)" || {
        CROSS_MISSING+=("all targets: /usr/bin/rustc does not run: $rv")
        return 1
    }
    _cross_say "Debian's $rv (rustc-web $CROSS_RUSTC_VERSION)"
    CROSS_OK+=(x86_64-unknown-linux-gnu)

    if _cross_foreign_std arm64 "$CROSS_RUSTC_VERSION"; then
        CROSS_OK+=(aarch64-unknown-linux-gnu)
    else
        CROSS_MISSING+=("aarch64-unknown-linux-gnu: $_cross_reason")
    fi

    if _cross_foreign_std armhf "$CROSS_RUSTC_VERSION"; then
        CROSS_OK+=(armv7-unknown-linux-gnueabihf)
    else
        local why="$_cross_reason"
        # Fallback: the armv7 std compiled from the compiler's own source.
        if _cross_install rust-web-src && [[ "$(_cross_installed rust-web-src)" == "$CROSS_RUSTC_VERSION" ]] &&
            [[ -f /usr/lib/rustlib/src/rust/library/Cargo.lock ]]; then
            _cross_say "armv7: $why; its std is compiled from rust-web-src $CROSS_RUSTC_VERSION instead (-Zbuild-std)"
            CROSS_ARMV7_BUILD_STD=1
            CROSS_OK+=(armv7-unknown-linux-gnueabihf)
        else
            CROSS_MISSING+=("armv7-unknown-linux-gnueabihf: $why; rust-web-src $CROSS_RUSTC_VERSION (to compile std) cannot be had either (installed: $(_cross_installed rust-web-src))")
        fi
    fi
    if [[ $with_qemu -eq 1 ]]; then
        for q in qemu-aarch64-static qemu-arm-static; do
            command -v "$q" >/dev/null || {
                CROSS_MISSING+=("qemu: $q not found after installing qemu-user-static")
                return 1
            }
        done
    fi
    return 0
}

# Builds klipcal for TRIPLE with cargo profile PROFILE using Debian's toolchain; prints the
# binary's path (armv7 with its std compiled: target dir $CROSS_TARGET_DIR-std). With CROSS_TIME_FILE set, GNU time writes there the build's wall, user and
# system seconds and the peak resident memory (kB) of its largest single process. Target dir: $CROSS_TARGET_DIR (under target/, out of git).
cross_build() {
    local triple="$1" profile="$2" gnu u extra=() dir="$CROSS_TARGET_DIR"
    gnu="$(_cross_gnu "$triple")"
    u="$(tr 'a-z-' 'A-Z_' <<<"$triple")"
    if [[ "$triple" == armv7-* && $CROSS_ARMV7_BUILD_STD -eq 1 ]]; then
        extra=(-Zbuild-std=std,panic_abort)
        # Its own target dir: build scripts see RUSTC_BOOTSTRAP (proc-macro2's reruns when it
        # changes), and sharing the host artifacts would rebuild everything at each switch.
        dir="$CROSS_TARGET_DIR-std"
    fi
    (
        unset RUSTUP_TOOLCHAIN RUSTFLAGS CARGO_BUILD_TARGET
        export RUSTC=/usr/bin/rustc RUSTDOC=/usr/bin/rustdoc CARGO_TARGET_DIR="$dir"
        export "CC_${triple//-/_}=$gnu-gcc" "AR_${triple//-/_}=$gnu-ar"
        export "CARGO_TARGET_${u}_LINKER=$gnu-gcc"
        [[ ${#extra[@]} -gt 0 ]] && export RUSTC_BOOTSTRAP=1
        timer=()
        [[ -n "${CROSS_TIME_FILE:-}" ]] && timer=(/usr/bin/time -f '%e %U %S %M' -o "$CROSS_TIME_FILE")
        # The printer's binary: the daemon alone (no benchmark crate, no simulator): what is
        # tested under qemu is what ships.
        "${timer[@]}" /usr/bin/cargo build --locked --profile "$profile" --target "$triple" -p klipcal \
            --bin klipcal "${extra[@]}" --quiet 1>&2
    ) || return 1
    local pdir="$profile"
    [[ "$profile" == dev ]] && pdir=debug
    echo "$dir/$triple/$pdir/klipcal"
}
