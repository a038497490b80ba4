#!/usr/bin/env python3
"""plant.py: the bench's thermal plant. Reads the bed and nozzle heater power
that Klipper's own PID computes (klippy's API socket, objects/query) and writes
the temperatures the `klipcal_file` sensors read. Owns the physics only; it
never sets a target or a power (that is Klipper's job).

Each heater is two coupled first-order masses and an ambient loss:

    C_h dT_h/dt = P * 1 - (T_h - T_p) / R_hp        heater element
    C_p dT_p/dt = (T_h - T_p) / R_hp - (T_p - T_a) / R_pa    plate

and the sensor reading lags T_h by a first-order sensor_tau_s,
with power P in 0..1. Parameters per heater (JSON):
  gain_c        steady rise above ambient at full power: R_hp + R_pa
  split         R_hp / (R_hp + R_pa), 0..1 (how much of the rise sits between
                heater and plate; larger = stronger power decay at constant T)
  tau_heater_s  C_h * R_hp: how fast the element follows power (plate fixed)
  sensor_tau_s  first-order lag of the thermistor behind the element
  tau_plate_s   relaxation time of the plate with the element held at
                constant temperature: C_p * R_hp*R_pa/(R_hp+R_pa). At constant
                sensor temperature the power decays with this time constant
                from (T-T_a)/(split*gain_c) to (T-T_a)/gain_c.
The frame (for thermal bed-mesh compensation) is two more first-order nodes:
a gantry warmed by the bed plate and a frame thermistor that lags the gantry,

    dT_g/dt = (T_a + gain * (T_plate_bed - T_a) - T_g) / tau_s
    dT_f/dt = (T_g - T_f) / lag_s

so at the same frame reading the gantry is warmer while heating than while
cooling (a slight hysteresis of the bow). Parameters under "frame": gain
(0..1), tau_s, lag_s, noise_c. The bench's simulated probe reads the gantry
temperature (comms/gantry_temp, hidden from klippy), the frame thermistor
`[temperature_sensor frame]` reads comms/frame_temp.
The chamber (an enclosure's air, for the soak's chamber thermometer): under
"chamber", initial_c (default: ambient) warming by warm_c_per_s of simulated
time until warm_until_s of simulated time, then flat; noise_c. It is written to
comms/chamber_temp, which `[temperature_sensor chamber]` reads in the bench's
chamber variant (bench.py --variant chamber).
Global: accel (simulated seconds per real second), ambient_c, noise_c
(gaussian sd added to each written reading), seed, period_s (real seconds
between updates), initial_c (start temperature, default ambient).

Files written in --run-dir/comms: bed_temp, nozzle_temp, frame_temp,
gantry_temp, chamber_temp (one number each,
replaced atomically) and plant_state.json (sim time, temperatures, powers).
"""
import argparse
import json
import math
import os
import random
import select
import signal
import socket
import sys
import time

DEFAULTS = {
    "accel": 1.0,
    "ambient_c": 25.0,
    "noise_c": 0.0,
    "seed": 1,
    "period_s": 0.05,
    "bed": {"gain_c": 120.0, "split": 0.5, "tau_heater_s": 30.0,
            "tau_plate_s": 240.0, "sensor_tau_s": 2.0},
    "nozzle": {"gain_c": 300.0, "split": 0.3, "tau_heater_s": 6.0,
               "tau_plate_s": 20.0, "sensor_tau_s": 1.0},
    "frame": {"gain": 0.15, "tau_s": 3600.0, "lag_s": 120.0, "noise_c": 0.0},
    "chamber": {"warm_c_per_s": 0.0, "warm_until_s": 0.0, "noise_c": 0.0},
}


class Frame:
    """Gantry + frame thermistor, warmed by the bed plate (see top)."""

    def __init__(self, p, ambient_c, initial_c):
        self.gain = float(p["gain"])
        self.tau_s = float(p["tau_s"])
        self.lag_s = float(p["lag_s"])
        if not (0 <= self.gain <= 1 and self.tau_s > 0 and self.lag_s > 0):
            raise ValueError("bad frame parameters %r: need 0<=gain<=1, "
                             "tau_s>0, lag_s>0" % (p,))
        self.noise_c = float(p.get("noise_c", 0.0))
        self.ambient_c = ambient_c
        self.t_gantry = self.t_frame = initial_c
        self.max_dt = min(self.tau_s, self.lag_s) / 20.0

    def step(self, dt_s, plate_c):
        n = max(1, int(math.ceil(dt_s / self.max_dt)))
        h = dt_s / n
        goal = self.ambient_c + self.gain * (plate_c - self.ambient_c)
        for _ in range(n):
            self.t_gantry += h * (goal - self.t_gantry) / self.tau_s
            self.t_frame += h * (self.t_gantry - self.t_frame) / self.lag_s


class Chamber:
    """An enclosure's air: warming at a steady rate for a while, then flat."""

    def __init__(self, p, ambient_c):
        self.initial_c = float(p.get("initial_c", ambient_c))
        self.rate = float(p["warm_c_per_s"])
        self.until_s = float(p["warm_until_s"])
        self.noise_c = float(p.get("noise_c", 0.0))
        if not (self.until_s >= 0 and self.noise_c >= 0):
            raise ValueError("bad chamber parameters %r: need warm_until_s>=0, "
                             "noise_c>=0" % (p,))

    def temp(self, sim_t):
        return self.initial_c + self.rate * min(sim_t, self.until_s)


HEATERS = {"bed": "heater_bed", "nozzle": "extruder"}


def merge(base, over):
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


class Mass2:
    """Heater element + plate, integrated with small explicit Euler steps."""

    def __init__(self, p, ambient_c, initial_c):
        gain = float(p["gain_c"])
        split = float(p["split"])
        if not (gain > 0 and 0 < split < 1 and p["tau_heater_s"] > 0
                and p["tau_plate_s"] > 0):
            raise ValueError("bad heater parameters %r: need gain_c>0, "
                             "0<split<1, tau_heater_s>0, tau_plate_s>0" % (p,))
        self.r_hp = split * gain
        self.r_pa = (1.0 - split) * gain
        self.c_h = p["tau_heater_s"] / self.r_hp
        self.c_p = p["tau_plate_s"] * gain / (self.r_hp * self.r_pa)
        self.sensor_tau_s = float(p.get("sensor_tau_s", 0.0))
        taus = [p["tau_heater_s"], p["tau_plate_s"] * split]
        if self.sensor_tau_s > 0:
            taus.append(self.sensor_tau_s)
        self.max_dt = min(taus) / 20.0
        self.ambient_c = ambient_c
        self.t_heater = self.t_plate = self.t_sensor = initial_c

    def step(self, dt_s, power):
        n = max(1, int(math.ceil(dt_s / self.max_dt)))
        h = dt_s / n
        for _ in range(n):
            q_hp = (self.t_heater - self.t_plate) / self.r_hp
            q_pa = (self.t_plate - self.ambient_c) / self.r_pa
            self.t_heater += h * (power - q_hp) / self.c_h
            self.t_plate += h * (q_hp - q_pa) / self.c_p
            if self.sensor_tau_s > 0:
                self.t_sensor += h * (self.t_heater - self.t_sensor) \
                    / self.sensor_tau_s
            else:
                self.t_sensor = self.t_heater


class Klippy:
    """Heater power from klippy's API socket (objects/subscribe: klippy pushes
    changes every 250 ms). Power reads 0 while klippy is down, as heaters are
    off when the host is."""

    def __init__(self, path):
        self.path = path
        self.sock = None
        self.buf = b""
        self.next_try = 0.0
        self.power = {k: 0.0 for k in HEATERS}

    def _connect(self):
        now = time.monotonic()
        if now < self.next_try:
            return False
        self.next_try = now + 0.5
        try:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(1.0)
            s.connect(self.path)
            req = {"id": 1, "method": "objects/subscribe",
                   "params": {"objects": {o: ["power"]
                                          for o in HEATERS.values()},
                              "response_template": {}}}
            s.sendall(json.dumps(req).encode() + b"\x03")
            s.setblocking(False)
            self.sock, self.buf = s, b""
            return True
        except OSError:
            return False

    def _drop(self):
        if self.sock is not None:
            self.sock.close()
        self.sock = None
        self.power = {k: 0.0 for k in HEATERS}

    def _apply(self, status):
        for k, obj in HEATERS.items():
            p = status.get(obj, {}).get("power")
            if p is not None:
                self.power[k] = float(p)

    def poll(self, timeout_s):
        """Waits up to timeout_s for updates; returns True when connected."""
        if self.sock is None and not self._connect():
            time.sleep(timeout_s)
            return False
        try:
            r, _, _ = select.select([self.sock], [], [], timeout_s)
            if not r:
                return True
            chunk = self.sock.recv(65536)
            if not chunk:
                raise OSError("klippy closed the socket")
            self.buf += chunk
            while b"\x03" in self.buf:
                msg, self.buf = self.buf.split(b"\x03", 1)
                m = json.loads(msg)
                if "error" in m:
                    raise OSError("klippy: %s" % m["error"])
                status = (m.get("result") or m.get("params") or {}).get(
                    "status", {})
                self._apply(status)
            return True
        except (OSError, ValueError):
            self._drop()
            return False


def write_atomic(path, text):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run-dir", required=True)
    ap.add_argument("--klippy-sock", required=True)
    ap.add_argument("--params", help="JSON file of parameters")
    ap.add_argument("--json", help="inline JSON parameters (after --params)")
    args = ap.parse_args()
    params = dict(DEFAULTS)
    try:
        if args.params and os.path.exists(args.params):
            with open(args.params) as f:
                params = merge(params, json.load(f))
        if args.json:
            params = merge(params, json.loads(args.json))
        ambient = float(params["ambient_c"])
        initial = float(params.get("initial_c", ambient))
        masses = {k: Mass2(params[k], ambient, initial) for k in HEATERS}
        frame = Frame(params["frame"], ambient, initial)
        chamber = Chamber(params["chamber"], ambient)
    except (OSError, ValueError, KeyError, TypeError) as e:
        sys.stderr.write("plant: bad parameters: %s\n" % e)
        sys.exit(2)
    comms = os.path.join(args.run_dir, "comms")
    rng = random.Random(params["seed"])
    accel = float(params["accel"])
    period = float(params["period_s"])
    noise = float(params["noise_c"])
    klippy = Klippy(args.klippy_sock)
    running = [True]
    signal.signal(signal.SIGTERM, lambda *_: running.__setitem__(0, False))
    sim_t = 0.0
    last = time.monotonic()
    n = 0
    sys.stdout.write("plant: started with %s\n" % json.dumps(params))
    sys.stdout.flush()
    connected = False
    next_step = time.monotonic()
    while running[0]:
        # Take power updates until the next physics step is due.
        while running[0]:
            wait = next_step - time.monotonic()
            if wait <= 0:
                break
            connected = klippy.poll(wait)
        next_step += period
        now = time.monotonic()
        dt_real = min(now - last, 1.0)
        last = now
        power = dict(klippy.power)
        dt_sim = dt_real * accel
        sim_t += dt_sim
        for k, m in masses.items():
            m.step(dt_sim, max(0.0, min(1.0, power[k])))
        frame.step(dt_sim, masses["bed"].t_plate)
        readings = {k: m.t_sensor + (rng.gauss(0.0, noise) if noise else 0.0)
                    for k, m in masses.items()}
        write_atomic(os.path.join(comms, "bed_temp"), "%.3f\n"
                     % readings["bed"])
        write_atomic(os.path.join(comms, "nozzle_temp"), "%.3f\n"
                     % readings["nozzle"])
        frame_c = frame.t_frame + (rng.gauss(0.0, frame.noise_c)
                                   if frame.noise_c else 0.0)
        write_atomic(os.path.join(comms, "frame_temp"), "%.4f\n" % frame_c)
        write_atomic(os.path.join(comms, "gantry_temp"), "%.4f\n"
                     % frame.t_gantry)
        chamber_c = chamber.temp(sim_t) + (rng.gauss(0.0, chamber.noise_c)
                                           if chamber.noise_c else 0.0)
        write_atomic(os.path.join(comms, "chamber_temp"), "%.4f\n" % chamber_c)
        n += 1
        if n % 5 == 0 or not running[0]:
            state = {"sim_t_s": round(sim_t, 3), "connected": connected,
                     "accel": accel}
            for k, m in masses.items():
                state[k] = {"heater_c": round(m.t_heater, 3),
                            "sensor_c": round(m.t_sensor, 3),
                            "plate_c": round(m.t_plate, 3),
                            "reading_c": round(readings[k], 3),
                            "power": power[k]}
            state["frame"] = {"gantry_c": round(frame.t_gantry, 4),
                              "frame_c": round(frame.t_frame, 4),
                              "reading_c": round(frame_c, 4)}
            state["chamber"] = {"reading_c": round(chamber_c, 4),
                                "warming": sim_t < chamber.until_s}
            write_atomic(os.path.join(comms, "plant_state.json"),
                         json.dumps(state))
        if next_step < time.monotonic() - 1.0:
            next_step = time.monotonic()

if __name__ == "__main__":
    main()
