#!/usr/bin/env python3
"""klipper_control_check.py: replays thermistor readings through Klipper's own
heater control (klippy/extras/heaters.py Heater.temperature_callback and
set_pwm, ControlPID; pid_calibrate.py ControlAutoTune and calc_final_pid) and
prints the pwm Klipper sets after each reading, so `klipcal bench soak` can
check its port of them (src/cmd/soak_four_node/klipper.rs) on the very same readings.
Needs the klippy venv:
  .bench/venv-klippy/bin/python tests/bench/klipper_control_check.py < runs.json

stdin: {"runs": [{"mode": "pid" | "autotune", "max_power": 1.0,
                  "smooth_time": 1.0, "pwm_delay": 0.3, "target": 60.0,
                  "gains": [Kp, Ki, Kd] (pid, Klipper's units),
                  "readings": [[read_time, temp], ...]}, ...]}
stdout: {"runs": [{"pwm": [last_pwm_value after each reading, ...],
                   "gains": [Kp, Ki, Kd] | null (autotune: calc_final_pid once
                   Klipper's wait would have ended), "updates": n}, ...]}

The Heater is Klipper's own class with only its constructor bypassed (no
config, no MCU): its set_pwm and temperature_callback run unchanged.
"""
import json
import sys
import threading

from klippy.extras import heaters, pid_calibrate


class _Pwm:
    """The MCU pin: records nothing (Heater keeps last_pwm_value itself)."""

    def set_pwm(self, print_time, value):
        pass


class _Config:
    def __init__(self, gains):
        self.v = dict(zip(("pid_Kp", "pid_Ki", "pid_Kd"), gains))

    def getfloat(self, name, *a, **kw):
        return self.v[name]


def _heater(run):
    h = object.__new__(heaters.Heater)
    h.name = "heater_bed"
    h.min_temp, h.max_temp = -273.15, 1000.0
    h.pwm_delay = float(run["pwm_delay"])
    h.min_extrude_temp = 170.0
    h.can_extrude = False
    h.max_power = float(run["max_power"])
    h.smooth_time = float(run["smooth_time"])
    h.inv_smooth_time = 1.0 / h.smooth_time
    h.lock = threading.Lock()
    h.last_temp = h.smoothed_temp = h.target_temp = 0.0
    h.last_temp_time = 0.0
    h.next_pwm_time = 0.0
    h.last_pwm_value = 0.0
    h.mcu_pwm = _Pwm()
    return h


def replay(run):
    h = _heater(run)
    target = float(run["target"])
    tuner = None
    if run["mode"] == "autotune":
        # PID_CALIBRATE: set_control(ControlAutoTune), then set_temperature.
        tuner = pid_calibrate.ControlAutoTune(h, target)
        h.control = tuner
    else:
        h.control = heaters.ControlPID(h, _Config(run["gains"]))
    h.set_temp(target)
    pwm = []
    gains = None
    for read_time, temp in run["readings"]:
        h.temperature_callback(read_time, temp)
        pwm.append(h.last_pwm_value)
        # Klipper's wait for the temperature ends once check_busy says so.
        if tuner is not None and not tuner.check_busy(0.0, 0.0, 0.0):
            gains = list(tuner.calc_final_pid())
            break
    return {"pwm": pwm, "gains": gains, "updates": len(pwm)}


def main():
    runs = json.load(sys.stdin)["runs"]
    json.dump({"runs": [replay(r) for r in runs]}, sys.stdout)


if __name__ == "__main__":
    main()
