#!/usr/bin/env python3
"""tune_pid.py: derives a bench run's PID gains offline by running Klipper's
own PID_CALIBRATE algorithm (ControlAutoTune) against plant.py's model with the
run's plant parameters and time acceleration, as real users tune a printer.
bench.py calls it at start (cached per parameter set) and writes the gains
into printer.cfg. Prints JSON {"bed": [Kp, Ki, Kd], "nozzle": [...]} in
Klipper's units for real time, scaled down from the autotune result when
Klipper's ControlPID with them would not settle on the plant (--check shows
the settling report and the scale). Needs the klippy venv:
  .bench/venv-klippy/bin/python tests/bench/tune_pid.py [--plant-json JSON] [--check]
(PID_CALIBRATE cannot run on the live bench: in file-output mode klippy's
heater wait returns at once.)

The loop is simulated in plant seconds: klippy samples every SAMPLE_S real
seconds and a new power reaches the plant DELAY_S real seconds later (klippy
pushes status every 0.25 s), both stretched by `accel`; the gains are then
converted back to real time (Ki * accel, Kd / accel).
"""
import argparse
import json
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from klippy.extras import heaters, pid_calibrate  # noqa: E402
import plant  # noqa: E402

SAMPLE_S = 0.25   # klipcal_bench sensor report time (real s)
DELAY_S = 0.2     # klippy push tick + plant step before power acts (real s)
SMOOTH_S = 1.0    # heaters' smooth_time default (real s)
TARGETS_C = {"bed": 60.0, "nozzle": 200.0}


class FakeHeater:
    """The parts of heaters.Heater the control classes call (plant seconds)."""

    def __init__(self, target_c, accel):
        self.target_c = target_c
        self.accel = accel
        self.pwm = 0.0
        self.pending = []

    def get_max_power(self):
        return 1.0

    def get_pwm_delay(self):
        return SAMPLE_S * self.accel

    def get_smooth_time(self):
        return SMOOTH_S * self.accel

    def set_pwm(self, read_time, value):
        self.pending.append((read_time + DELAY_S * self.accel, value))

    def alter_target(self, target_c):
        self.target_c = target_c


class FakeConfig:
    def __init__(self, kp, ki, kd):
        self.v = {"pid_Kp": kp, "pid_Ki": ki, "pid_Kd": kd}

    def getfloat(self, name, *a, **kw):
        return self.v[name]


def run(control, heater, mass, t_end_s, log=None):
    t = 0.0
    next_sample = 0.0
    sample_s = SAMPLE_S * heater.accel
    dt = min(0.01 * heater.accel, mass.max_dt)
    while t < t_end_s:
        while heater.pending and heater.pending[0][0] <= t:
            heater.pwm = heater.pending.pop(0)[1]
        mass.step(dt, heater.pwm)
        t += dt
        if t >= next_sample:
            next_sample += sample_s
            control.temperature_update(t, mass.t_sensor, heater.target_c)
            if log is not None:
                log.append((t, mass.t_sensor, heater.pwm))
            if isinstance(control, pid_calibrate.ControlAutoTune) and \
                    not control.check_busy(0, 0, 0):
                return


def tune(params, target_c, accel):
    """Klipper's autotune on the plant; gains in real-time units."""
    mass = plant.Mass2(params, 25.0, 25.0)
    heater = FakeHeater(target_c, accel)
    tuner = pid_calibrate.ControlAutoTune(heater, target_c)
    run(tuner, heater, mass, 200000.0)
    if tuner.check_busy(0, 0, 0):
        raise SystemExit("autotune did not converge for %r" % (params,))
    kp, ki, kd = tuner.calc_final_pid()
    return kp, ki * accel, kd / accel


def check(params, target_c, gains, accel, t_end_real_s=900.0):
    """Runs ControlPID with real-time gains; report in real seconds."""
    kp, ki, kd = gains
    mass = plant.Mass2(params, 25.0, 25.0)
    heater = FakeHeater(target_c, accel)
    ctl = heaters.ControlPID(heater, FakeConfig(kp, ki / accel, kd * accel))
    log = []
    run(ctl, heater, mass, t_end_real_s * accel, log)
    log = [(t / accel, c, p) for (t, c, p) in log]
    late = [p for (t, _, p) in log if t > t_end_real_s - 60]
    temps = [c for (t, c, _) in log if t > 60]
    return {"overshoot_c": round(max(temps) - target_c, 2),
            "power_sd_last_60s": round(statistics.pstdev(late), 4),
            "power_mean_last_60s": round(statistics.mean(late), 3),
            "power_at_60s": round([p for (t, _, p) in log if t > 60][0], 3),
            "temp_end_c": round(log[-1][1], 2)}


def tune_stable(params, target_c, accel):
    """Klipper's autotune, then the gains scaled down (all three alike) until
    ControlPID holds the target: with the dead time that sampling adds at
    high accel, Ziegler-Nichols gains can oscillate. Returns (gains, scale,
    check report)."""
    base = tune(params, target_c, accel)
    for scale in (1.0, 0.7, 0.5, 0.35, 0.25, 0.18, 0.12):
        gains = tuple(g * scale for g in base)
        rep = check(params, target_c, gains, accel, 400.0)
        if rep["power_sd_last_60s"] < 0.03 and rep["overshoot_c"] < 3.0 \
                and abs(rep["temp_end_c"] - target_c) < 0.5:
            return gains, scale, rep
    return gains, scale, rep


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plant-json", default="{}",
                    help="plant parameters as given to bench.py start")
    ap.add_argument("--check", action="store_true")
    args = ap.parse_args()
    params = plant.merge(plant.DEFAULTS, json.loads(args.plant_json))
    accel = float(params["accel"])
    out = {}
    for name in ("bed", "nozzle"):
        gains, scale, rep = tune_stable(params[name], TARGETS_C[name], accel)
        out[name] = [round(g, 4) for g in gains]
        if args.check:
            out[name + "_check"] = dict(rep, scale=scale)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
