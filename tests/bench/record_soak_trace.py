#!/usr/bin/env python3
"""Records a bed heat-up on the bench's real Klipper PID (klippy + the thermal plant) as a
soak-detect trace: `t_s,power,temp_c,target_c`, t_s in the plant's simulated seconds.

    record_soak_trace.py OUT.csv --tau-plate S [--accel 20] [--target 60] [--minutes 5]
                         [--every-s 10] [--noise-c 0.05]

Used once to make the fixtures tests/fixtures/soak/*.csv that `klipcal bench soak` reports as
its recorded family (issue 10 (c)); the bench itself is started and stopped here.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))


def query(http_url):
    url = http_url + "/printer/objects/query?heater_bed=temperature,target,power"
    with urllib.request.urlopen(url, timeout=5) as r:
        return json.load(r)["result"]["status"]["heater_bed"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--tau-plate", type=float, required=True)
    ap.add_argument("--accel", type=float, default=20.0)
    ap.add_argument("--target", type=float, default=60.0)
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--every-s", type=float, default=10.0)
    ap.add_argument("--noise-c", type=float, default=0.05)
    a = ap.parse_args()
    plant = {"accel": a.accel, "noise_c": a.noise_c,
             "bed": {"tau_plate_s": a.tau_plate}}
    run = tempfile.mkdtemp(prefix="kc-rec-")
    bench = [sys.executable, os.path.join(HERE, "bench.py")]
    out = subprocess.run(bench + ["start", "--run-dir", run, "--kinematics", "corexy",
                                  "--plant-json", json.dumps(plant)],
                         check=True, capture_output=True, text=True).stdout
    info = json.loads([l for l in out.splitlines() if l.startswith("{")][-1])
    http = info["http_url"]
    try:
        script = "SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=%g" % a.target
        urllib.request.urlopen(urllib.request.Request(
            http + "/printer/gcode/script?script=" + urllib.parse.quote(script),
            method="POST"), timeout=10).read()
        t0 = time.monotonic()
        rows = []
        next_sim = 0.0
        while time.monotonic() - t0 < a.minutes * 60.0:
            sim = (time.monotonic() - t0) * a.accel
            if sim >= next_sim:
                hb = query(http)
                rows.append((sim, hb["power"], hb["temperature"], hb["target"]))
                next_sim += a.every_s
            time.sleep(0.02)
        with open(a.out, "w") as f:
            f.write("# bench heat-up on Klipper's PID: plate tau %g s, accel %g, noise %g C\n"
                    % (a.tau_plate, a.accel, a.noise_c))
            f.write("t_s,power,temp_c,target_c\n")
            for r in rows:
                f.write("%.1f,%.4f,%.3f,%.1f\n" % r)
    finally:
        subprocess.run(bench + ["stop", "--run-dir", run], capture_output=True)


if __name__ == "__main__":
    import urllib.parse  # noqa: F401  (used above)
    main()
