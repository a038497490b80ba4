#!/usr/bin/env python3
"""gen_mcu_dict.py: writes mcu_dict.json, the MCU data dictionary klippy reads
in file-output mode (`-d`), since no MCU is there to send one. Owns the list of
command/response formats; they must equal klippy's own strings byte for byte
(mcu.py, stepper.py, clocksync.py, extras/*), as Klipper's firmware declares
them. Does not run klippy: `bench.py start`/`batch` do, and fail loudly on a
mismatch ("Command format mismatch" / "Unknown command").

Message ids must lie in -32..95 (klippy refuses multi-byte ids); 0 and 1 are
identify_response / identify.
"""
import json
import os
import sys

COMMANDS = [
    # base
    "get_uptime",
    "get_clock",
    "get_config",
    "finalize_config crc=%u",
    "allocate_oids count=%c",
    "emergency_stop",
    "clear_shutdown",
    "reset",
    # steppers
    "config_stepper oid=%c step_pin=%c dir_pin=%c invert_step=%c"
    " step_pulse_ticks=%u",
    "queue_step oid=%c interval=%u count=%hu add=%hi",
    "set_next_step_dir oid=%c dir=%c",
    "reset_step_clock oid=%c clock=%u",
    "stepper_get_position oid=%c",
    "stepper_stop_on_trigger oid=%c trsync_oid=%c",
    # endstops and trsync
    "config_endstop oid=%c pin=%c pull_up=%c",
    "endstop_home oid=%c clock=%u sample_ticks=%u sample_count=%c"
    " rest_ticks=%u pin_value=%c trsync_oid=%c trigger_reason=%c",
    "endstop_query_state oid=%c",
    "config_trsync oid=%c",
    "trsync_start oid=%c report_clock=%u report_ticks=%u expire_reason=%c",
    "trsync_set_timeout oid=%c clock=%u",
    "trsync_trigger oid=%c reason=%c",
    # gpio out
    "config_digital_out oid=%c pin=%u value=%c default_value=%c"
    " max_duration=%u",
    "set_digital_out_pwm_cycle oid=%c cycle_ticks=%u",
    "queue_digital_out oid=%c clock=%u on_ticks=%u",
    "update_digital_out oid=%c value=%c",
    "set_digital_out pin=%u value=%c",
    "config_pwm_out oid=%c pin=%u cycle_ticks=%u value=%hu"
    " default_value=%hu max_duration=%u",
    "queue_pwm_out oid=%c clock=%u value=%hu",
    "set_pwm_out pin=%u cycle_ticks=%u value=%hu",
    # adc
    "config_analog_in oid=%c pin=%u",
    "query_analog_in oid=%c clock=%u sample_ticks=%u sample_count=%c"
    " rest_ticks=%u min_value=%hu max_value=%hu range_check_count=%c",
]

RESPONSES = [
    "starting",
    "is_shutdown static_string_id=%hu",
    "shutdown clock=%u static_string_id=%hu",
    "stats count=%u sum=%u sumsq=%u",
    "uptime high=%u clock=%u",
    "clock clock=%u",
    "config is_config=%c crc=%u is_shutdown=%c move_count=%hu",
    "stepper_position oid=%c pos=%i",
    "endstop_state oid=%c homing=%c next_clock=%u pin_value=%c",
    "trsync_state oid=%c can_trigger=%c trigger_reason=%c clock=%u",
    "analog_in_state oid=%c next_clock=%u value=%hu",
]

CONFIG = {
    "MCU": "stm32f446xx",
    "CLOCK_FREQ": 180000000,
    "ADC_MAX": 4095,
    "PWM_MAX": 255,
    "STATS_SUMSQ_BASE": 256,
    "STEPPER_BOTH_EDGE": 1,
}

# Ports A..H with 16 pins each: PA0..PA15 = 0..15, PB0 = 16, ...
PINS = {"P%s0" % port: [16 * i, 16] for i, port in enumerate("ABCDEFGH")}


def build():
    commands = {"identify offset=%u count=%c": 1}
    responses = {"identify_response offset=%u data=%.*s": 0}
    next_id = 2
    for fmt in COMMANDS:
        commands[fmt] = next_id
        next_id += 1
    for fmt in RESPONSES:
        responses[fmt] = next_id
        next_id += 1
    if next_id > 96:
        raise SystemExit("too many messages for single-byte ids: %d" % next_id)
    return {
        "version": "klipcal-bench-fake-mcu",
        "build_versions": "none",
        "app": "Klipper",
        "license": "GNU GPLv3",
        "config": CONFIG,
        "enumerations": {"pin": PINS},
        "commands": commands,
        "responses": responses,
        "output": {},
    }


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(here,
                                                             "mcu_dict.json")
    with open(out, "w") as f:
        json.dump(build(), f, indent=1, sort_keys=True)
        f.write("\n")
    print(out)


if __name__ == "__main__":
    main()
