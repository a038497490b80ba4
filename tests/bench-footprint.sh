#!/usr/bin/env bash
# Footprint benchmark: starts a bench (real Moonraker + klippy + thermal plant) and the printer's
# release daemon (built as release.sh builds it: the daemon alone, no benchmarks) connected and subscribed to it, then `klipcal bench footprint` samples for SECONDS
# (default 60) and prints klipcal's RSS and CPU beside Moonraker's and klippy's RSS.
# Targets: klipcal RSS <= 1/10 of Moonraker's with the page open; CPU < 0.5 % of one core on
# average; release binary <= 20 MiB; start to "connected to Moonraker" <= 2 s.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
seconds="${1:-60}"
bash tests/bench/setup.sh >/dev/null
# The daemon measured is the printer's binary; the measuring tool is the checkout's own build.
cargo build --release --quiet -p klipcal --target-dir target/printer
cargo build --workspace --quiet
printer_bin=target/printer/release/klipcal
run="$(mktemp -d /tmp/kc-fp-XXXXXX)"
cleanup() {
    [[ -n "${daemon:-}" ]] && kill "$daemon" 2>/dev/null || true
    python3 tests/bench/bench.py stop --run-dir "$run" >/dev/null 2>&1 || true
    rm -rf "$run"
}
trap cleanup EXIT
info="$(python3 tests/bench/bench.py start --run-dir "$run" | tail -n 1)"
field() { python3 -c "import json,sys; v=json.loads(sys.argv[1]); print(eval('v'+sys.argv[2]))" "$info" "$1"; }
ws="$(field '["ws_url"]')"
# Heat the bed so status updates keep flowing while we measure.
curl -s -X POST "$(field '["http_url"]')/printer/gcode/script?script=SET_HEATER_TEMPERATURE%20HEATER=heater_bed%20TARGET=60" >/dev/null
# The daemon with its page on a free loopback port; start-up is timed to "connected".
port="$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')"
printf '[http]\nbind = "127.0.0.1:%s"\n' "$port" >"$run/klipcal.toml"
t0="$(date +%s%N)"
HOME="$run" "$printer_bin" --config "$run/klipcal.toml" --moonraker "$ws" serve 2>"$run/klipcal.log" &
daemon=$!
for _ in $(seq 1 200); do
    grep -q "connected to Moonraker" "$run/klipcal.log" 2>/dev/null && break
    sleep 0.01
done
t1="$(date +%s%N)"
startup_ms=$(( (t1 - t0) / 1000000 ))
sleep 3
./target/debug/klipcal bench footprint --klipcal-pid "$daemon" \
    --moonraker-pid "$(field '["pids"]["moonraker"]')" --klippy-pid "$(field '["pids"]["klippy"]')" \
    --seconds "$seconds" --binary "$printer_bin" --startup-ms "$startup_ms" \
    --page-url "http://127.0.0.1:$port"
