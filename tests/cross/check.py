#!/usr/bin/env python3
"""check.py: runs klipcal binaries built for other architectures (under qemu-user) beside the
x86_64 one and checks that they behave the same. Called by tests/cross/run.sh; stdlib only.

  check.py --ref PATH --bin ARCH=PATH [--bin ARCH=PATH ...] --work DIR [--install-arch ARCH]

1. Each binary prints --version.
2. The offline commands (pylons, solve, mesh fit, mesh profiles, backlash solve, soak-detect,
   and a few refused inputs) on the same inputs give byte-identical stdout, stderr, exit code
   and written files to the reference binary's (--ref, x86_64).
3. On one bench (tests/bench/bench.py: a real Moonraker and klippy), each binary as the daemon
   registers with Moonraker as the agent `klipcal`, with no remote method refused, and answers
   KLIPCAL_STATUS run through Klipper (Moonraker's printer/gcode/script; the answer read back
   from Moonraker's gcode store); then stops on SIGTERM with status 0. `install --dry-run`
   against the bench's printer_data names that binary's asset and writes nothing.
4. --install-arch: that binary runs `klipcal install` into the bench's printer_data, set up as a
   new user has it: release_info.json names its asset, the copy is byte-identical, Moonraker
   (restarted by install) lists klipcal in its update manager as an executable of this version
   without a warning, and the installed copy, as the daemon, answers KLIPCAL_STATUS through the
   macros install wrote.

Prints one line per check and a closing "N passed, N failed"; exits 1 on any failure.
"""

import argparse
import difflib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
QEMU = {
    "aarch64": ["qemu-aarch64-static", "-L", "/usr/aarch64-linux-gnu"],
    "armv7": ["qemu-arm-static", "-L", "/usr/arm-linux-gnueabihf"],
    "x86_64": [],
}

passed = 0
failed = []


def check(name, ok, detail=""):
    global passed
    if ok:
        passed += 1
        print(f"ok    {name}", flush=True)
    else:
        failed.append(name)
        print(f"FAIL  {name}\n      {detail}".rstrip(), flush=True)
    return ok


def cmd_of(arch, path):
    return QEMU[arch] + [path]


def run(cmd, args, cwd=None, env=None, timeout=300):
    e = dict(os.environ)
    e.update(env or {})
    t = time.monotonic()
    p = subprocess.run(cmd + args, cwd=cwd, env=e, capture_output=True, timeout=timeout)
    return p.returncode, p.stdout, p.stderr, time.monotonic() - t


# ---------------------------------------------------------------- offline inputs

def mesh_cfg():
    """A printer.cfg whose SAVE_CONFIG block holds VGB-named meshes of a bed that bows as the
    frame warms (5x5, a COLD, five HOT and two TEST meshes), with a deterministic wobble."""
    rng = random.Random(28)
    temps = [("COLD", 24.8), ("HOT", 28.1), ("HOT", 31.9), ("TEST", 33.4), ("HOT", 35.2),
             ("HOT", 38.7), ("TEST", 40.1), ("HOT", 42.3)]
    out = ["[printer]", "kinematics: corexy", "", "[bed_mesh]", "mesh_min: 20, 20",
           "mesh_max: 280, 280", "probe_count: 5, 5", "",
           "#*# <---------------------- SAVE_CONFIG ---------------------->",
           "#*# DO NOT EDIT THIS BLOCK OR BELOW. The contents are auto-generated.", "#*#"]
    for kind, t in temps:
        out += [f"#*# [bed_mesh {kind}{t:.1f}]", "#*# version = 1", "#*# points ="]
        bow = 0.004 * (t - 24.0)
        for j in range(5):
            v = (j - 2) / 2.0
            row = []
            for i in range(5):
                u = (i - 2) / 2.0
                z = 0.03 * u - 0.02 * v + bow * (u * u + v * v) - 0.5 * bow * u * v
                z += rng.gauss(0.0, 0.0015)
                row.append(f"{z:.6f}")
            out.append("#*# \t" + ", ".join(row))
        out += ["#*# x_count = 5", "#*# y_count = 5", "#*# mesh_x_pps = 2", "#*# mesh_y_pps = 2",
                "#*# algo = lagrange", "#*# tension = 0.2", "#*# min_x = 20.0",
                "#*# max_x = 280.0", "#*# min_y = 20.0", "#*# max_y = 280.0", "#*#"]
    return "\n".join(out) + "\n"


def readings_for(layout):
    """Caliper readings for every pair of a layout: group A a little long, B a little short,
    five readings each with a deterministic spread."""
    rng = random.Random(7)
    scale = {"A": 1.0024, "B": 0.9983, "X": 1.0011, "Y": 0.9992}
    out = {}
    for p in layout["pairs"]:
        s = scale.get(p["group"], 1.0)
        out[p["id"]] = [round(p["nominal_mm"] * s + rng.gauss(0, 0.006), 2) for _ in range(5)]
    return out


def backlash_readings():
    rng = random.Random(4)
    out = {}
    for axis, b in (("x", 0.085), ("y", 0.032), ("z", 0.004)):
        cyc = []
        for k in range(8):
            x1 = 100.0 + rng.gauss(0, 0.004)
            cyc.append([round(x1, 4), round(x1 - b + rng.gauss(0, 0.005), 4)])
        if axis == "x":
            cyc.append([100.0, 99.6])  # an outlier
        out[axis] = cyc
    return out


def klippy_log_from(csv_path):
    """A klippy.log built from a recorded bed trace, as tests/it/cli.rs builds one."""
    lines = ["Starting Klippy...", "===== Config file =====", "[heater_bed]",
             "control = pid", "max_power = 0.8", "======================="]
    for k in range(30):
        lines.append(f"Stats {1000 + k}.0: gcodein=0 heater_bed: target=0 temp=22.0 pwm=0.000")
    n = 0
    with open(csv_path) as f:
        for line in f:
            if not line[:1].isdigit():
                continue
            t, power, temp, target = line.strip().split(",")[:4]
            stamp = "12:25:06.344: " if n % 2 == 0 else ""
            lines.append(f"{stamp}Stats {1030.0 + float(t):.1f}: gcodein=0 mcu: mcu_awake=0.003 "
                         f"heater_bed: target={target} temp={temp} pwm={power} sysload=0.1")
            n += 1
    return "\n".join(lines) + "\n"


def offline_cases():
    real = os.path.join(REPO, "tests/fixtures/soak/real")
    traces = [os.path.join(real, "besser435-ted-4.csv")]
    cases = [
        ("pylons paper", ["pylons", "--printer-cfg", "../in/printer.cfg", "--out", "out/p.gcode",
                          "--layout-out", "out/layout.json", "--svg", "out/p.svg"]),
        ("pylons full, other sizes", ["pylons", "--printer-cfg", "../in/printer.cfg",
                                      "--layout", "full", "--d2", "120", "--bed-temp", "65",
                                      "--nozzle-temp", "225", "--pylon-length", "40",
                                      "--out", "out/full.gcode", "--layout-out", "out/full.json"]),
        ("solve", ["solve", "--layout", "../in/layout.json", "--readings", "../in/readings.json",
                   "--printer-cfg", "../in/printer.cfg"]),
        ("solve --json (csv readings, klipper-skew)",
         ["solve", "--json", "--layout", "../in/layout.json", "--readings", "../in/readings.csv",
          "--printer-cfg", "../in/printer.cfg", "--shear-to", "klipper-skew"]),
        ("mesh fit", ["mesh", "fit", "--printer-cfg", "../in/mesh.cfg"]),
        ("mesh fit --json", ["mesh", "fit", "--json", "--printer-cfg", "../in/mesh.cfg"]),
        ("mesh profiles", ["mesh", "profiles", "--printer-cfg", "../in/mesh.cfg",
                           "--tolerance-um", "3", "--out", "out/block.cfg"]),
        ("mesh profiles --json", ["mesh", "profiles", "--json", "--printer-cfg", "../in/mesh.cfg",
                                  "--from", "26", "--to", "41", "--out", "out/block2.cfg"]),
        ("backlash solve", ["backlash", "solve", "--readings", "../in/backlash.json",
                            "--max-accel", "3000"]),
        ("backlash solve --json", ["backlash", "solve", "--json", "--readings",
                                   "../in/backlash.json"]),
        ("soak-detect --klippy-log", ["soak-detect", "--klippy-log", "../in/klippy.log"]),
        ("soak-detect --klippy-log --json", ["soak-detect", "--json", "--klippy-log",
                                             "../in/klippy.log"]),
        ("refused: readings with a word", ["solve", "--layout", "../in/layout.json",
                                           "--readings", "../in/bad-readings.json",
                                           "--printer-cfg", "../in/printer.cfg"]),
        ("refused: no such file", ["mesh", "fit", "--printer-cfg", "../in/none.cfg"]),
    ]
    for t in traces:
        name = os.path.basename(t)
        cases.append((f"soak-detect {name}", ["soak-detect", "--trace", t]))
        cases.append((f"soak-detect --json {name}", ["soak-detect", "--json", "--trace", t]))
    return cases


NO_FMA = "x86_64-no-fma-libm"
STAMP = re.compile(rb"^; generated by klipcal (\S+) on \d{4}-\d\d-\d\d at \d\d:\d\d:\d\d UTC$",
                   re.M)


def normalize(b):
    """The G-code's first line says when it was generated: the time is taken out."""
    return STAMP.sub(rb"; generated by klipcal \1 on <date> at <time> UTC", b)


def tree(d):
    out = {}
    for root, _dirs, files in os.walk(d):
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, d)] = fh.read()
    return out


def first_difference(a, b, what):
    a_t = a.decode("utf-8", "replace").splitlines()
    b_t = b.decode("utf-8", "replace").splitlines()
    d = list(difflib.unified_diff(a_t, b_t, "x86_64", "this", lineterm="", n=1))
    return f"{what} differs:\n      " + "\n      ".join(d[:12])


def offline(work, ref, bins, printer_dir):
    inp = os.path.join(work, "in")
    os.makedirs(inp, exist_ok=True)
    for f in os.listdir(printer_dir):
        if f.endswith(".cfg"):
            shutil.copy(os.path.join(printer_dir, f), inp)
    with open(os.path.join(inp, "mesh.cfg"), "w") as f:
        f.write(mesh_cfg())
    with open(os.path.join(inp, "backlash.json"), "w") as f:
        json.dump(backlash_readings(), f)
    with open(os.path.join(inp, "klippy.log"), "w") as f:
        f.write(klippy_log_from(os.path.join(REPO, "tests/fixtures/soak/real/ryszardwpl-vzbot-old-1.csv")))
    # The layout solve reads: the reference's pylons output, the same file for every binary.
    rc, _o, e, _t = run([ref], ["pylons", "--printer-cfg", os.path.join(inp, "printer.cfg"),
                                "--out", os.path.join(inp, "p.gcode"),
                                "--layout-out", os.path.join(inp, "layout.json")])
    if not check("reference pylons writes the layout solve reads", rc == 0, e.decode()):
        return
    with open(os.path.join(inp, "layout.json")) as f:
        layout = json.load(f)
    readings = readings_for(layout)
    with open(os.path.join(inp, "readings.json"), "w") as f:
        json.dump(readings, f)
    with open(os.path.join(inp, "readings.csv"), "w") as f:
        f.write("pair,reading\n")
        for k, vs in readings.items():
            for v in vs:
                f.write(f"{k},{v}\n")
    bad = dict(readings)
    bad[next(iter(bad))] = [10.01, "ten"]
    with open(os.path.join(inp, "bad-readings.json"), "w") as f:
        json.dump(bad, f)

    cases = offline_cases()
    results = {}
    # Two x86_64 references: as it runs here, and with glibc's FMA code paths of libm (exp, log,
    # pow, ...) switched off. Those differ in the last bits of some results (e.g. soak-detect
    # --json's 16-digit numbers); armv7 (VFPv3, no FMA) takes glibc's plain paths, aarch64 the
    # FMA ones. Every other binary must match one of the two byte for byte, in every command.
    runs = [("x86_64", [ref], {}),
            (NO_FMA, [ref], {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-FMA,-AVX2"})]
    runs += [(a, cmd_of(a, p), {}) for a, p in bins]
    for arch, cmd, env in runs:
        d = os.path.join(work, arch)
        shutil.rmtree(d, ignore_errors=True)
        os.makedirs(os.path.join(d, "out"))
        t0 = time.monotonic()
        slow = []
        for name, args in cases:
            rc, o, e, t = run(cmd, args, cwd=d, env=env)
            results[(arch, name)] = (rc, normalize(o), e)
            slow.append((t, name))
        results[(arch, "files")] = {k: normalize(v) for k, v in tree(os.path.join(d, "out")).items()}
        slow.sort(reverse=True)
        print(f"      {arch}: {len(cases)} offline commands in {time.monotonic() - t0:.1f} s "
              f"(slowest: " + ", ".join(f"{n} {t:.1f} s" for t, n in slow[:3]) + ")", flush=True)
    # The reference itself must have done the work: every command that should succeed did,
    # with output; the refused ones were refused with a message.
    for name, _args in cases:
        rc, o, e = results[("x86_64", name)]
        if name.startswith("refused"):
            check(f"x86_64 {name}: refused with a message", rc != 0 and len(e) > 20, e.decode())
        else:
            check(f"x86_64 {name}: succeeds with output", rc == 0 and len(o) > 20,
                  f"rc {rc}: {e.decode()[-600:]}")
    ref_files = results[("x86_64", "files")]
    check("x86_64 wrote the G-code, layouts, SVG and profile blocks",
          {"p.gcode", "layout.json", "p.svg", "full.gcode", "full.json", "block.cfg",
           "block2.cfg"} <= set(ref_files), sorted(ref_files))
    fma_differs = [n for n, _a in cases if results[("x86_64", n)] != results[(NO_FMA, n)]]
    print(f"      x86_64 with and without libm's FMA paths differ in: {fma_differs or 'nothing'}")
    for arch, _p in bins:
        best = None
        for refname in ("x86_64", NO_FMA):
            bad = []
            for name, _args in cases:
                rc, o, e = results[(arch, name)]
                rrc, ro, re_ = results[(refname, name)]
                if rc != rrc:
                    bad.append((name, f"exit {rc}, {refname} {rrc}: {e.decode()[-600:]}"))
                elif not same_but_last_bits(o, ro):
                    bad.append((name, first_difference(ro, o, "stdout")))
                elif not same_but_last_bits(e, re_):
                    bad.append((name, first_difference(re_, e, "stderr")))
            files = results[(arch, "files")]
            rfiles = results[(refname, "files")]
            diff = sorted(k for k in set(files) | set(rfiles)
                          if not same_but_last_bits(files.get(k), rfiles.get(k)))
            if diff:
                bad.append((f"written files {diff}", first_difference(
                    rfiles.get(diff[0], b""), files.get(diff[0], b""), diff[0])))
            if best is None or len(bad) < len(best[1]):
                best = (refname, bad)
        refname, bad = best
        check(f"{arch}: {len(cases)} offline commands' stdout, stderr, exit status and "
              f"{len(ref_files)} written files identical to {refname}'s (numbers to 9 digits)",
              not bad,
              "\n      ".join(f"{n}: {d}" for n, d in bad[:4]))


NUMBER = re.compile(rb"-?\d+\.\d+(?:[eE][-+]?\d+)?")


def same_but_last_bits(a, b):
    """The same text, and the same numbers to 9 significant digits: the math library's last
    bits differ between FMA and plain code paths (aarch64's libm takes other paths than
    x86_64's), and a difference of readings that agree to 0.01 mm amplifies them (solve's
    uncertainty differed by 2e-10 relative), and a quantity that is zero but for rounding
    (a perfect fit's chi2, 9e-24 against 5e-24) differs in every digit, hence the 1e-15 floor;
    an overflow, a size assumption or a wrong branch on 32 bits would differ far more."""
    if a == b:
        return True
    if a is None or b is None:
        return False
    if NUMBER.sub(b"#", a) != NUMBER.sub(b"#", b):
        return False
    for x, y in zip(NUMBER.findall(a), NUMBER.findall(b)):
        fx, fy = float(x), float(y)
        if abs(fx - fy) > 1e-9 * max(abs(fx), abs(fy)) + 1e-15:
            return False
    return True


# ---------------------------------------------------------------- the bench

class Moonraker:
    def __init__(self, http_url):
        self.url = http_url

    def req(self, method, path, body=None, timeout=10):
        data = None if body is None else json.dumps(body).encode()
        r = urllib.request.Request(self.url + path, data=data, method=method,
                                   headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(r, timeout=timeout) as resp:
            return json.loads(resp.read())["result"]

    def get(self, path):
        return self.req("GET", path)

    def post(self, path, body):
        return self.req("POST", path, body, timeout=30)

    def poll(self, limit_s, fn):
        end = time.monotonic() + limit_s
        while time.monotonic() < end:
            try:
                v = fn()
                if v:
                    return v
            except (urllib.error.URLError, OSError, KeyError, ValueError):
                pass
            time.sleep(0.25)
        return None

    def ready(self, limit_s=90):
        return self.poll(limit_s, lambda: self.get("/server/info")["klippy_state"] == "ready")

    def agent_listed(self):
        return any(a.get("name") == "klipcal"
                   for a in self.get("/server/extensions/list").get("agents", []))


def bench_py(*args):
    p = subprocess.run([sys.executable, os.path.join(REPO, "tests/bench/bench.py"), *args],
                       capture_output=True, text=True, timeout=180)
    if p.returncode != 0:
        raise RuntimeError(f"bench.py {' '.join(args)}: {p.stdout}{p.stderr}")
    return p.stdout


def klipcal_status(mr, arch, daemon_cmd, toml, log_path, label):
    """Starts the daemon, checks registration and KLIPCAL_STATUS through Klipper, stops it."""
    with open(log_path, "wb") as log:
        child = subprocess.Popen(daemon_cmd + ["--config", toml, "serve"], stdin=subprocess.DEVNULL,
                                 stdout=subprocess.DEVNULL, stderr=log,
                                 env=dict(os.environ, RUST_LOG="klipcal=debug"))
    try:
        t0 = time.monotonic()
        listed = mr.poll(120, mr.agent_listed)
        logtext = lambda: open(log_path, errors="replace").read()  # noqa: E731
        if not check(f"{label}: registers with Moonraker as agent klipcal "
                     f"({time.monotonic() - t0:.1f} s)", listed, logtext()[-1500:]):
            return

        def answered(since):
            store = mr.get("/server/gcode_store?count=100")["gcode_store"]
            lines = [s["message"] for s in store
                     if s["type"] == "response" and s["time"] >= since]
            if any("rotation_distance" in m for m in lines) and \
                    any("connected, Klipper ready" in m for m in lines):
                return lines
            return None
        # Moonraker lists the agent before its remote methods are registered: a macro run in
        # between gets "Unknown method"; it is run again (three tries at most).
        lines = None
        for _try in range(3):
            since = time.time()
            mr.post("/printer/gcode/script", {"script": "KLIPCAL_STATUS"})
            lines = mr.poll(20, lambda: answered(since))
            if lines:
                break
        check(f"{label}: answers KLIPCAL_STATUS run through Klipper", lines,
              logtext()[-1500:])
        if lines:
            print("      " + " | ".join(m for m in lines if "klipcal" in m)[:300])
        check(f"{label}: every remote method registered", "could not register" not in logtext(),
              logtext()[-1500:])
    finally:
        child.send_signal(signal.SIGTERM)
        try:
            rc = child.wait(30)
        except subprocess.TimeoutExpired:
            child.kill()
            rc = "no exit within 30 s"
        check(f"{label}: stops on SIGTERM with status 0", rc == 0, f"status {rc}")


def snapshot(pd):
    out = {}
    for sub in ("config",):
        d = os.path.join(pd, sub)
        for f in sorted(os.listdir(d)):
            p = os.path.join(d, f)
            if os.path.isfile(p) and not f.startswith("."):
                with open(p, "rb") as fh:
                    out[p] = fh.read()
    for p in (os.path.join(pd, "moonraker.asvc"),):
        out[p] = open(p, "rb").read() if os.path.exists(p) else b""
    for d in os.listdir(pd):
        if d.startswith("klipcal-bin"):
            out[os.path.join(pd, d)] = b"exists"
    return out


def on_bench(work, bins, install_arch):
    run_dir = os.path.join(work, "bench")
    shutil.rmtree(run_dir, ignore_errors=True)
    info = json.loads(bench_py("start", "--run-dir", run_dir, "--owner-pid", str(os.getpid())))
    try:
        mr = Moonraker(info["http_url"])
        check("bench: Klipper ready", mr.ready(), "")
        toml = os.path.join(run_dir, "klipcal.toml")
        with open(toml, "w") as f:
            f.write(f'[moonraker]\nurl = "{info["ws_url"]}"\nreconnect_min_s = 0.2\n'
                    f'reconnect_max_s = 1.0\n[daemon]\ndata_dir = "{run_dir}/klipcal-data"\n'
                    '[http]\nbind = "127.0.0.1:0"\n')
        env = {"HOME": run_dir}
        for arch, path in bins:
            cmd = cmd_of(arch, path)
            klipcal_status(mr, arch, cmd, toml, os.path.join(run_dir, f"klipcal-{arch}.log"),
                           f"{arch} daemon")
            before = snapshot(run_dir)
            rc, o, e, _t = run(cmd, ["--moonraker", info["ws_url"], "install", "--printer-data",
                                     run_dir, "--bin-dir", f"{run_dir}/klipcal-bin-{arch}",
                                     "--no-systemd", "--dry-run"], env=env)
            out = (o + e).decode("utf-8", "replace")
            asset = f"klipcal-{arch}-linux"
            check(f"{arch} install --dry-run: prints the update_manager entry and names "
                  f"{asset}", rc == 0 and "+[update_manager klipcal" in out and
                  "+type: executable" in out and f'"asset_name": "{asset}"' in out and
                  f"klipcal-bin-{arch}/{asset}" in out, out[-2000:])
            check(f"{arch} install --dry-run writes nothing", snapshot(run_dir) == before,
                  sorted(k for k in set(before) | set(snapshot(run_dir))
                         if before.get(k) != snapshot(run_dir).get(k)))
        if install_arch:
            install(mr, info, run_dir, dict(bins)[install_arch], install_arch, toml)
    finally:
        bench_py("stop", "--run-dir", run_dir)


def install(mr, info, pd, binary, arch, toml):
    cfg = os.path.join(pd, "config")
    # A printer as a new user has it: no include, no macros, no [respond]; Moonraker with its
    # update manager on.
    with open(os.path.join(cfg, "printer.cfg")) as f:
        printer = f.read().replace("[include klipcal.cfg]", "").replace("[respond]\n", "")
    with open(os.path.join(cfg, "printer.cfg"), "w") as f:
        f.write(printer)
    os.remove(os.path.join(cfg, "klipcal.cfg"))
    with open(os.path.join(cfg, "moonraker.conf"), "a") as f:
        f.write("\n[update_manager]\nenable_system_updates: False\n")
    mr.post("/server/restart", {})
    time.sleep(2)
    check("bench restarted as a new user's printer", mr.ready(), "")
    bin_dir = os.path.join(pd, "klipcal")
    asset = f"klipcal-{arch}-linux"
    rc, o, e, t = run(cmd_of(arch, binary),
                      ["--moonraker", info["ws_url"], "install", "--printer-data", pd,
                       "--bin-dir", bin_dir, "--no-systemd", "--yes"], env={"HOME": pd})
    out = (o + e).decode("utf-8", "replace")
    if not check(f"{arch} install ({t:.1f} s under qemu)", rc == 0, out[-2000:]):
        return
    try:
        with open(os.path.join(bin_dir, "release_info.json")) as f:
            rinfo = json.load(f)
    except (OSError, ValueError) as err:
        rinfo = {"error": str(err)}
    check(f"release_info.json names {asset}",
          rinfo.get("asset_name") == asset and rinfo.get("version", "").startswith("v"), rinfo)
    copy = os.path.join(bin_dir, asset)
    same = os.path.isfile(copy) and open(copy, "rb").read() == open(binary, "rb").read()
    check(f"{copy} is the {arch} binary, byte for byte", same, os.listdir(bin_dir))
    with open(os.path.join(cfg, "moonraker.conf")) as f:
        conf = f.read()
    # The section is named after the printer's service: klipcal for ~/printer_data, klipcal-<folder>
    # for another folder (issue 25 D: two printers on one host).
    m = re.search(r"\[update_manager (klipcal[^\]]*)\]", conf)
    um_name = m.group(1) if m else "klipcal"
    sect = conf[conf.find(f"[update_manager {um_name}]"):]
    check("moonraker.conf has [update_manager klipcal…] of type executable with repo: and path:",
          m is not None and "type: executable" in sect and
          "\nrepo: " in sect and f"path: {bin_dir}" in sect, conf[-600:])
    check("Moonraker and Klipper back after install's restart", mr.ready(), "")
    warnings = json.dumps(mr.get("/server/info").get("warnings", []))
    check("Moonraker has no warning about klipcal", "klipcal" not in warnings.lower(), warnings)

    def listed():
        v = mr.get("/machine/update/status")["version_info"].get(um_name)
        return v or None
    upd = mr.poll(60, listed) or {}
    check("Moonraker's update manager accepts it: executable, version "
          f"{rinfo.get('version')}, no warning",
          upd.get("configured_type") == "executable" and upd.get("version") == rinfo.get("version")
          and not upd.get("warnings") and not upd.get("anomalies"), json.dumps(upd)[:800])
    # The installed copy serves the macros install wrote.
    klipcal_status(mr, arch, cmd_of(arch, copy), toml, os.path.join(pd, "klipcal-installed.log"),
                   f"installed {asset} daemon")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ref", required=True, help="the x86_64 klipcal the others are compared to")
    ap.add_argument("--bin", action="append", default=[], help="ARCH=PATH (aarch64, armv7, x86_64)")
    ap.add_argument("--work", required=True)
    ap.add_argument("--install-arch", default="")
    a = ap.parse_args()
    bins = []
    for b in a.bin:
        arch, path = b.split("=", 1)
        if arch not in QEMU:
            sys.exit(f"check.py: --bin {b}: unknown arch {arch}")
        bins.append((arch, os.path.abspath(path)))
    os.makedirs(a.work, exist_ok=True)
    work = os.path.abspath(a.work)
    ref = os.path.abspath(a.ref)
    t0 = time.monotonic()
    for arch, path in [("x86_64", ref)] + bins:
        rc, o, e, t = run(cmd_of(arch, path), ["--version"])
        check(f"{arch} --version ({os.path.getsize(path) / 1e6:.1f} MB, {t:.2f} s)",
              rc == 0 and o.decode().startswith("klipcal "), (o + e).decode())
    # The printer config the offline commands read: the bench's own, rendered once.
    cfg_run = os.path.join(work, "cfg-bench")
    shutil.rmtree(cfg_run, ignore_errors=True)
    bench_py("start", "--run-dir", cfg_run, "--owner-pid", str(os.getpid()))
    bench_py("stop", "--run-dir", cfg_run)
    offline(work, ref, bins, os.path.join(cfg_run, "config"))
    print(f"      offline checks done in {time.monotonic() - t0:.1f} s", flush=True)
    t1 = time.monotonic()
    on_bench(work, bins, a.install_arch)
    print(f"      bench checks done in {time.monotonic() - t1:.1f} s", flush=True)
    print(f"cross: {passed} passed, {len(failed)} failed")
    for f in failed:
        print(f"  failed: {f}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
