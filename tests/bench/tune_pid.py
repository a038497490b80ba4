#!/usr/bin/env python3
"""tune_pid.py: derives the bench's PID gains (bench.py PID_GAINS) offline by
running Klipper's own PID_CALIBRATE algorithm (ControlAutoTune) and ControlPID
against plant.py's model at accel 1, then checks the loop settles. Needs the
klippy venv:  .bench/venv-klippy/bin/python tests/bench/tune_pid.py
Owns nothing at run time; it only prints gains and a settling report.
(PID_CALIBRATE cannot run on the live bench: in file-output mode klippy's
heater wait returns at once.)
"""
import json
import os
import statistics
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from klippy.extras import heaters, pid_calibrate  # noqa: E402
import plant  # noqa: E402

SAMPLE_S = 0.25   # klipcal_bench sensor report time
DELAY_S = 0.1     # plant poll latency before a new power takes effect


class FakeHeater:
    """The parts of heaters.Heater the control classes call."""

    def __init__(self, target_c):
        self.target_c = target_c
        self.pwm = 0.0
        self.pending = []

    def get_max_power(self):
        return 1.0

    def get_pwm_delay(self):
        return SAMPLE_S

    def get_smooth_time(self):
        return 1.0

    def set_pwm(self, read_time, value):
        self.pending.append((read_time + DELAY_S, value))

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
    dt = 0.01
    while t < t_end_s:
        while heater.pending and heater.pending[0][0] <= t:
            heater.pwm = heater.pending.pop(0)[1]
        mass.step(dt, heater.pwm)
        t += dt
        if t >= next_sample:
            next_sample += SAMPLE_S
            control.temperature_update(t, mass.t_sensor, heater.target_c)
            if log is not None:
                log.append((t, mass.t_sensor, heater.pwm))
            if isinstance(control, pid_calibrate.ControlAutoTune) and \
                    not control.check_busy(0, 0, 0):
                return


def tune(params, target_c):
    mass = plant.Mass2(params, 25.0, 25.0)
    heater = FakeHeater(target_c)
    tuner = pid_calibrate.ControlAutoTune(heater, target_c)
    run(tuner, heater, mass, 20000.0)
    return tuner.calc_final_pid()


def check(params, target_c, gains, t_end_s):
    mass = plant.Mass2(params, 25.0, 25.0)
    heater = FakeHeater(target_c)
    ctl = heaters.ControlPID(heater, FakeConfig(*gains))
    log = []
    run(ctl, heater, mass, t_end_s, log)
    late = [p for (t, _, p) in log if t > t_end_s - 60]
    temps = [c for (t, c, _) in log if t > 60]
    return {"overshoot_c": round(max(temps) - target_c, 2),
            "power_sd_last_60s": round(statistics.pstdev(late), 4),
            "power_mean_last_60s": round(statistics.mean(late), 3),
            "power_at_120s": round([p for (t, _, p) in log if t > 120][0], 3),
            "temp_end_c": round(log[-1][1], 2)}


def main():
    out = {}
    for name, target in (("bed", 60.0), ("nozzle", 200.0)):
        params = plant.DEFAULTS[name]
        gains = tune(params, target)
        out[name] = {"gains": [round(g, 3) for g in gains],
                     "check": check(params, target, gains, 900.0)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
