#!/usr/bin/env bash
# Try klipcal without a printer: a simulated printer (a real Klipper host and a real Moonraker
# from PyPI, a simulated MCU and bed) with the klipcal daemon connected to it.
#
#   scripts/try-bench.sh [ab|mesh|backlash] [--cartesian] [--smoke]
#
#   ab        (default) CoreXY 300 mm; try KLIPCAL_AB_START, KLIPCAL_MEASURE, KLIPCAL_AB_SOLVE…
#   mesh      adds a simulated probe and a frame thermistor: KLIPCAL_MESH_CAPTURE, _FOLLOW, _CHECK
#   backlash  adds PR 7259's [backlash_compensation] and 80 µm of play on X/A:
#             KLIPCAL_BACKLASH_SET_POINT, KLIPCAL_BACKLASH_START AXIS=X
#   --cartesian   a Cartesian 235 mm printer instead (X/Y instead of A/B)
#   --smoke       start, check that a macro reaches klipcal through Klipper, stop (for tests)
#   KLIPCAL_BIN=path   run that klipcal binary instead of building one
#
# The bed runs 20 times faster than real time and the soak settings are short, so a whole A/B
# round takes a few minutes. Everything lives in one folder under ${TMPDIR:-/tmp}; Ctrl-C stops
# the daemon and the simulated printer.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

what=ab
kin=corexy
smoke=0
for a in "$@"; do
    case "$a" in
        ab|mesh|backlash) what=$a ;;
        --cartesian) kin=cartesian ;;
        --smoke) smoke=1 ;;
        -h|--help) sed -n '2,18p' "$0"; exit 0 ;;
        *) echo "try-bench: unknown argument $a; expected ab, mesh, backlash, --cartesian, --smoke" >&2; exit 2 ;;
    esac
done

say() { echo "try-bench: $*"; }

bash tests/bench/setup.sh >/dev/null
if [[ -n "${KLIPCAL_BIN:-}" ]]; then
    bin="$KLIPCAL_BIN"
else
    say "building klipcal (cargo build)"
    cargo build --quiet --bin klipcal
    bin="target/debug/klipcal"
fi

run="$(mktemp -d "${TMPDIR:-/tmp}/klipcal-try-XXXXXX")"
extra=()
case "$what" in
    mesh) extra+=(--variant mesh) ;;
    backlash)
        if [[ $kin == corexy ]]; then play='{"a": 0.08, "b": 0.05}'; else play='{"x": 0.08, "y": 0.05}'; fi
        extra+=(--backlash-module seed --play "$play") ;;
esac
plant='{"accel": 20, "bed": {"tau_plate_s": 100.0, "tau_heater_s": 20.0}}'
info="$(python3 tests/bench/bench.py start --run-dir "$run" --kinematics "$kin" \
    --plant-json "$plant" --owner-pid $$ "${extra[@]}")"
ws="$(python3 -c 'import json,sys; print(json.loads(sys.argv[1])["ws_url"])' "$info")"
http="$(python3 -c 'import json,sys; print(json.loads(sys.argv[1])["http_url"])' "$info")"
http="${http%/}"
page_port="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"

stop() {
    [[ -n "${daemon:-}" ]] && kill "$daemon" 2>/dev/null && wait "$daemon" 2>/dev/null || true
    python3 tests/bench/bench.py stop --run-dir "$run" >/dev/null 2>&1 || true
    if [[ $smoke == 1 ]]; then rm -rf "$run"; fi
}
trap stop EXIT

# The settings of the bench tests: a fast soak, a short cool-down, small mesh captures.
cat >"$run/klipcal.toml" <<EOF
[moonraker]
url = "$ws"
[daemon]
data_dir = "$run/klipcal-data"
[http]
bind = "127.0.0.1:$page_port"
[ab]
bed_temp_c = 60.0
cooldown_s = 0.0
hold_max_s = 1800.0
soak_max_s = 600.0
[soak]
settle_s = 1.0
bin_s = 0.5
min_soak_s = 3.0
tau_max_s = 30.0
max_remaining = 0.03
[mesh]
bed_temp_c = 60.0
step_c = 0.5
interval_s = 120.0
min_meshes = 3
max_meshes = 4
max_s = 900.0
EOF

"$bin" --config "$run/klipcal.toml" serve 2>"$run/klipcal.log" &
daemon=$!

# Wait until klipcal answers a macro run by Klipper.
script() { curl -fsS -X POST -H 'Content-Type: application/json' \
    -d "{\"script\": \"$1\"}" "$http/printer/gcode/script" >/dev/null; }
answered=0
for _ in $(seq 1 60); do
    if script KLIPCAL_STATUS 2>/dev/null &&
       curl -fsS "$http/server/gcode_store?count=20" | grep -q 'klipcal [0-9.]* connected'; then
        answered=1; break
    fi
    sleep 1
done
if [[ $answered != 1 ]]; then
    say "klipcal did not answer KLIPCAL_STATUS; its log:"; cat "$run/klipcal.log" >&2
    exit 1
fi
say "klipcal answered KLIPCAL_STATUS through Klipper"
[[ $smoke == 1 ]] && exit 0

cat <<EOF

  A simulated $kin printer ($what) with klipcal, in $run
    Moonraker   $http   (point Mainsail or Fluidd at it, or use curl as below)
    klipcal     http://127.0.0.1:$page_port/   (its page)
    logs        $run/logs/klippy.log, $run/logs/moonraker.log, $run/klipcal.log

  Run a macro as Mainsail's console would:
    curl -X POST -H 'Content-Type: application/json' -d '{"script": "KLIPCAL_STATUS"}' $http/printer/gcode/script
    curl "$http/server/gcode_store?count=30"     # the console

  Ctrl-C stops everything.
EOF
wait "$daemon"
