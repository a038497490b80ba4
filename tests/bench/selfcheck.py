#!/usr/bin/env python3
"""selfcheck.py: end-to-end check of the bench by hand (not part of cargo test):
starts two runs in parallel (CoreXY with an accelerated plant, Cartesian),
then checks heater control, an uploaded print to completion, pause/resume/
cancel, exclude_object, KLIPCAL_STATUS reaching a websocket client, bed-mesh
and skew profiles, SAVE_CONFIG, FIRMWARE_RESTART, restarting Moonraker and
klippy with start-one/stop-one, batch mode, and that stop leaves no process.
Run with the Moonraker venv (it has tornado for the websocket client):
  .bench/venv-moonraker/bin/python tests/bench/selfcheck.py [WORK_DIR]
Prints one line per check and exits non-zero on the first failure.
"""
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request

from tornado.websocket import websocket_connect

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = [sys.executable, os.path.join(HERE, "bench.py")]
T0 = time.time()


def log(msg):
    print("[%6.1fs] %s" % (time.time() - T0, msg), flush=True)


def fail(msg):
    log("FAIL: " + msg)
    sys.exit(1)


def bench(*args, check=True):
    p = subprocess.run(BENCH + list(args), capture_output=True, text=True)
    if check and p.returncode != 0:
        fail("bench.py %s: %s" % (" ".join(args), p.stderr))
    return p


def get(info, path):
    with urllib.request.urlopen(info["http_url"] + path, timeout=30) as r:
        return json.loads(r.read())["result"]


def post(info, path, timeout=60):
    req = urllib.request.Request(info["http_url"] + path, data=b"",
                                 method="POST")
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())["result"]


def gcode(info, script, timeout=60):
    return post(info, "/printer/gcode/script?script="
                + urllib.parse.quote(script), timeout)


def query(info, *objs):
    return get(info, "/printer/objects/query?" + "&".join(objs))["status"]


def upload(info, name, text):
    boundary = "klipcalbenchboundary"
    body = ("--%s\r\nContent-Disposition: form-data; name=\"file\"; "
            "filename=\"%s\"\r\nContent-Type: application/octet-stream\r\n\r\n"
            "%s\r\n--%s--\r\n" % (boundary, name, text, boundary)).encode()
    req = urllib.request.Request(
        info["http_url"] + "/server/files/upload", data=body, method="POST",
        headers={"Content-Type": "multipart/form-data; boundary=" + boundary})
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.loads(r.read())


def wait_for(what, fn, timeout_s):
    deadline = time.time() + timeout_s
    last = None
    while time.time() < deadline:
        try:
            last = fn()
            if last:
                return last
        except Exception as e:  # server restarting
            last = e
        time.sleep(0.2)
    fail("timed out waiting for %s (last: %r)" % (what, last))


def print_state(info):
    return query(info, "print_stats")["print_stats"]["state"]


def wait_ready(info, timeout_s=30):
    return wait_for("klippy ready", lambda: get(info, "/server/info")[
        "klippy_state"] == "ready", timeout_s)


PRINT = """
PRINT_START BED=0 EXTRUDER=0
EXCLUDE_OBJECT_DEFINE NAME=pylon_a CENTER=100,100 POLYGON=[[95,95],[105,95],[105,105],[95,105]]
EXCLUDE_OBJECT_DEFINE NAME=pylon_b CENTER=200,200 POLYGON=[[195,195],[205,195],[205,205],[195,205]]
G1 Z0.2 F600
EXCLUDE_OBJECT_START NAME=pylon_a
G1 X95 Y95 F6000
G1 X105 Y95 E0.5 F1800
G1 X105 Y105 E0.5
EXCLUDE_OBJECT_END NAME=pylon_a
EXCLUDE_OBJECT_START NAME=pylon_b
G1 X195 Y195 F6000
G1 X205 Y195 E0.5 F1800
EXCLUDE_OBJECT_END NAME=pylon_b
BENCH_SLEEP SECONDS=%(sleep)s
G1 X150 Y150 F6000
PRINT_END
"""


async def remote_method_roundtrip(info):
    ws = await websocket_connect(info["ws_url"])

    async def call(method, params, rid):
        await ws.write_message(json.dumps({"jsonrpc": "2.0", "method": method,
                                           "params": params, "id": rid}))

    await call("server.connection.identify",
               {"client_name": "klipcal-selfcheck", "version": "0",
                "type": "agent", "url": "http://localhost"}, 1)
    await call("connection.register_remote_method",
               {"method_name": "klipcal_status"}, 2)
    await asyncio.sleep(0.3)
    await call("printer.gcode.script", {"script": "KLIPCAL_STATUS"}, 3)
    deadline = time.time() + 10
    while time.time() < deadline:
        msg = await asyncio.wait_for(ws.read_message(), 10)
        if msg is None:
            break
        m = json.loads(msg)
        if m.get("method") == "klipcal_status":
            ws.close()
            return m
    ws.close()
    return None


def main():
    work = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(
        prefix="klipcal-selfcheck-")
    a_dir, b_dir = os.path.join(work, "a"), os.path.join(work, "b")
    log("starting two runs in parallel under %s" % work)
    t = time.time()
    pa = subprocess.Popen(BENCH + ["start", "--run-dir", a_dir, "--plant-json",
                                   '{"accel": 10, "noise_c": 0.02}'],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True)
    pb = subprocess.Popen(BENCH + ["start", "--run-dir", b_dir, "--kinematics",
                                   "cartesian"], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True)
    out_a, err_a = pa.communicate()
    out_b, err_b = pb.communicate()
    if pa.returncode or pb.returncode:
        fail("start: %s %s" % (err_a, err_b))
    a, b = json.loads(out_a), json.loads(out_b)
    log("both ready in %.1f s (ports %d, %d)" % (time.time() - t,
                                                  a["moonraker_port"],
                                                  b["moonraker_port"]))
    try:
        checks(a, b)
    finally:
        for d in (a_dir, b_dir):
            r = bench("stop", "--run-dir", d, check=False)
            log("stop %s: %s" % (d, r.stdout.strip() or r.stderr.strip()))
    for info in (a, b):
        for name, pid in info["pids"].items():
            if os.path.exists("/proc/%d" % pid):
                with open("/proc/%d/stat" % pid) as f:
                    if f.read().rsplit(")", 1)[1].split()[0] != "Z":
                        fail("%s pid %d still running after stop" % (name,
                                                                     pid))
    log("stop left no process behind")
    batch_checks(work)
    log("ALL CHECKS PASSED")


def checks(a, b):
    # Cartesian variant loaded
    kin = query(b, "configfile")["configfile"]["settings"]["printer"][
        "kinematics"]
    if kin != "cartesian":
        fail("run b kinematics %s" % kin)
    log("cartesian variant ready (kinematics=%s)" % kin)

    # Heater follows the target; power decays at constant temperature
    gcode(a, "SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=60")
    samples = []
    for _ in range(100):  # each query answers on klippy's 250 ms tick
        s = query(a, "heater_bed")["heater_bed"]
        samples.append((time.time(), s["temperature"], s["power"]))
    at = [i for i, (_, c, _) in enumerate(samples) if c >= 59.5]
    if not at:
        fail("bed never reached 60: %r" % samples[-1:])
    i0 = at[0]
    early = [p for (_, _, p) in samples[i0:i0 + 12]]
    late = [p for (_, _, p) in samples[-12:]]
    temps_late = [c for (_, c, _) in samples[-12:]]
    pe, pl = sum(early) / len(early), sum(late) / len(late)
    log("bed reached 60 after %.1f s; power %.3f -> %.3f; late temps %.2f..%.2f"
        % (samples[i0][0] - samples[0][0], pe, pl, min(temps_late),
           max(temps_late)))
    if not (pl < pe - 0.05 and max(abs(c - 60) for c in temps_late) < 1.0):
        fail("expected power to decay at constant temperature")
    gcode(a, "SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=0")

    # Upload and print to completion, with exclude_object
    r = upload(a, "bench_ok.gcode", PRINT % {"sleep": 0.5})
    log("uploaded: %s" % r["item"]["path"])
    post(a, "/printer/print/start?filename=bench_ok.gcode")
    wait_for("print complete", lambda: print_state(a) == "complete", 60)
    eo = query(a, "exclude_object")["exclude_object"]
    log("print complete; exclude_object objects=%s" %
        [o["name"] for o in eo["objects"]])
    if len(eo["objects"]) != 2:
        fail("exclude_object objects %r" % eo)

    # Pause / resume / exclude during a BENCH_SLEEP; the sleep's rest runs
    upload(a, "bench_8s.gcode", PRINT % {"sleep": 8})
    t_start = time.time()
    post(a, "/printer/print/start?filename=bench_8s.gcode")
    wait_for("printing", lambda: print_state(a) == "printing", 20)
    time.sleep(1.0)
    t = time.time()
    post(a, "/printer/print/pause")
    wait_for("paused", lambda: print_state(a) == "paused", 20)
    log("paused during BENCH_SLEEP in %.1f s" % (time.time() - t))
    time.sleep(2.0)
    post(a, "/printer/print/resume")
    wait_for("printing again", lambda: print_state(a) == "printing", 20)
    time.sleep(2.0)
    if print_state(a) != "printing":
        fail("after RESUME the rest of BENCH_SLEEP should still run")
    gcode(a, "EXCLUDE_OBJECT NAME=PYLON_B")
    ex = query(a, "exclude_object")["exclude_object"]["excluded_objects"]
    wait_for("complete", lambda: print_state(a) == "complete", 30)
    ps = query(a, "print_stats")["print_stats"]
    log("resume, exclude (%s), complete after %.1f s wall, print_duration "
        "%.1f s" % (ex, time.time() - t_start, ps["print_duration"]))
    if ps["print_duration"] < 7.0:
        fail("BENCH_SLEEP SECONDS=8 should make the print last >= 8 s")

    # Cancel during a long sleep, then reprint: the sleep starts afresh
    upload(a, "bench_long.gcode", PRINT % {"sleep": 60})
    for attempt in range(2):
        post(a, "/printer/print/start?filename=bench_long.gcode")
        wait_for("printing", lambda: print_state(a) == "printing", 20)
        time.sleep(3.0)
        if print_state(a) != "printing":
            fail("long print stopped early (attempt %d)" % attempt)
        t = time.time()
        post(a, "/printer/print/cancel")
        wait_for("cancelled", lambda: print_state(a) == "cancelled", 20)
        log("cancel during BENCH_SLEEP took %.1f s" % (time.time() - t))

    # KLIPCAL_STATUS reaches a websocket client
    m = asyncio.run(remote_method_roundtrip(a))
    if not m:
        fail("KLIPCAL_STATUS did not call the remote method")
    log("KLIPCAL_STATUS -> remote method %s" % m["method"])

    # Profiles
    gcode(a, "BED_MESH_PROFILE LOAD=hot")
    gcode(a, "SKEW_PROFILE LOAD=bench_skew")
    bm = query(a, "bed_mesh")["bed_mesh"]
    log("bed_mesh profile=%s profiles=%s" % (bm["profile_name"],
                                             sorted(bm["profiles"])))
    if bm["profile_name"] != "hot":
        fail("bed mesh profile not loaded")
    gcode(a, "SET_SKEW XY=141.4,141.4,100 CLEAR=0")
    gcode(a, "SKEW_PROFILE SAVE=selfcheck")
    gcode(a, "BED_MESH_PROFILE SAVE=copy")

    # SAVE_CONFIG restarts klippy and keeps the include
    t = time.time()
    try:
        gcode(a, "SAVE_CONFIG", timeout=30)
    except Exception as e:  # klippy restarts under the request
        log("SAVE_CONFIG request ended with %s" % e)
    time.sleep(1.0)
    wait_ready(a)
    cfg = open(a["printer_cfg"]).read()
    ok = ("[include steppers.cfg]" in cfg and "#*# [bed_mesh copy]" in cfg
          and "#*# [skew_correction selfcheck]" in cfg)
    log("SAVE_CONFIG + restart in %.1f s; profiles saved: %s" % (
        time.time() - t, ok))
    if not ok:
        fail("SAVE_CONFIG did not write the expected sections")

    # FIRMWARE_RESTART
    t = time.time()
    try:
        gcode(a, "FIRMWARE_RESTART", timeout=30)
    except Exception:
        pass
    time.sleep(0.5)
    wait_ready(a)
    log("FIRMWARE_RESTART back to ready in %.1f s" % (time.time() - t))

    # Kill and restart Moonraker, then klippy, on the same ports/dirs
    t = time.time()
    bench("stop-one", "moonraker", "--run-dir", a["run_dir"])
    r = json.loads(bench("start-one", "moonraker", "--run-dir",
                         a["run_dir"]).stdout)
    if r["moonraker_port"] != a["moonraker_port"]:
        fail("port changed")
    wait_ready(a)
    log("moonraker restarted (pid %d) ready in %.1f s" % (
        r["pids"]["moonraker"], time.time() - t))
    t = time.time()
    bench("stop-one", "klippy", "--run-dir", a["run_dir"])
    wait_for("moonraker sees klippy gone", lambda: get(a, "/server/info")[
        "klippy_state"] != "ready", 20)
    r = json.loads(bench("start-one", "klippy", "--run-dir",
                         a["run_dir"]).stdout)
    wait_ready(a)
    log("klippy restarted (pid %d) ready in %.1f s" % (r["pids"]["klippy"],
                                                      time.time() - t))
    a["pids"] = r["pids"]


def batch_checks(work):
    ok_g = os.path.join(work, "ok.gcode")
    bad_g = os.path.join(work, "bad.gcode")
    with open(ok_g, "w") as f:
        f.write("G28\nG1 Z0.2 F600\nG1 X10 Y10 F6000\nG1 X110 Y110 E5 F1800\n")
    with open(bad_g, "w") as f:
        f.write("G28\nG1 X200 Y10 F6000\n")
    r = bench("batch", "--kinematics", "corexy", "--size", "120", "--gcode",
              ok_g, check=False)
    j = json.loads(r.stdout)
    if r.returncode != 0 or not j["ok"]:
        fail("batch ok.gcode: %s" % r.stdout)
    log("batch ok.gcode on 120 corexy: ok in %.1f s" % j["elapsed_s"])
    r = bench("batch", "--kinematics", "cartesian", "--size", "120",
              "--gcode", bad_g, check=False)
    j = json.loads(r.stdout)
    if r.returncode == 0 or j["ok"] or not any("out of range" in e
                                               for e in j["errors"]):
        fail("batch bad.gcode should fail with out of range: %s" % r.stdout)
    log("batch bad.gcode rejected: %s" % j["errors"])


if __name__ == "__main__":
    main()
