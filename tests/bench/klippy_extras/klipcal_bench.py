# klipcal_bench: test-bench helpers for running klippy without an MCU
# (file-output mode, `-o OUT -d DICT`). Owns (a) the `klipcal_file` temperature
# sensor type, read from a file the bench's thermal plant writes, and (b) the
# BENCH_SLEEP G-code. Must not touch heater control: Klipper's own PID heater
# computes the power from these readings.
#
# Load it with a bare [klipcal_bench] section placed BEFORE [extruder] and
# [heater_bed] in printer.cfg: klippy builds sections in file order, and the
# heaters look the sensor type up while they are being built, so the factory
# must already be registered.
#
# Why not temperature_host: in file-output mode it returns before starting its
# timer, and mcu.estimated_print_time() is always 0 there, so readings would all
# carry the same time and the PID's integral and derivative would never move.
# Readings here are stamped with real reactor time (seconds since this module
# loaded), which also keeps the heater's pwm clocks small.
#
# In batch mode (-i FILE) every G-code response is also written to the log as
# "klipcal_bench response: ..." (klippy has nowhere else to send it there).
#
# Config of a sensor (in [extruder] / [heater_bed]):
#   sensor_type: klipcal_file
#   sensor_file: /abs/path/bed_temp     # one number, degrees C
#   ambient_temp: 25                    # used until the file exists
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import logging

REPORT_TIME_S = 0.25


class FileTemperatureSensor:
    """Temperature sensor reading a number (deg C) from a file at 4 Hz."""

    def __init__(self, config, bench):
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.bench = bench
        self.name = config.get_name().split()[-1]
        self.path = config.get('sensor_file')
        self.temp_c = config.getfloat('ambient_temp', 25.)
        self.min_temp_c = self.max_temp_c = 0.
        self._callback = None
        self.bad_reads = 0
        self.sample_timer = self.reactor.register_timer(self._sample)
        self.printer.register_event_handler("klippy:connect",
                                            self._handle_connect)

    def _handle_connect(self):
        self.reactor.update_timer(self.sample_timer, self.reactor.NOW)

    # Interface used by heaters.Heater
    def setup_minmax(self, min_temp, max_temp):
        self.min_temp_c = min_temp
        self.max_temp_c = max_temp

    def setup_callback(self, cb):
        self._callback = cb

    def get_report_time_delta(self):
        return REPORT_TIME_S

    def _read(self):
        try:
            with open(self.path, 'r') as f:
                return float(f.read().strip())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            # The plant rewrites the file atomically; a bad read is rare.
            self.bad_reads += 1
            if self.bad_reads % 20 == 1:
                logging.warning("klipcal_file %s: unreadable %s",
                                self.name, self.path)
            return None

    def _sample(self, eventtime):
        value = self._read()
        if value is not None:
            self.temp_c = value
        if self.temp_c < self.min_temp_c or self.temp_c > self.max_temp_c:
            self.printer.invoke_shutdown(
                "klipcal_file %s: temperature %.1f outside %.1f..%.1f"
                % (self.name, self.temp_c, self.min_temp_c, self.max_temp_c))
            return self.reactor.NEVER
        if self._callback is not None:
            self._callback(self.bench.read_time(eventtime), self.temp_c)
        return eventtime + REPORT_TIME_S

    def get_status(self, eventtime):
        return {'temperature': round(self.temp_c, 2)}


class KlipcalBench:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.t0 = self.reactor.monotonic()
        # (print file, position) of a BENCH_SLEEP cut short, and its rest;
        # forgotten when the print file is reset (cancel, new print).
        self.interrupted = None
        self.printer.register_event_handler("virtual_sdcard:reset_file",
                                            self._forget_interrupted)
        # Fault injection for rollback tests: refuse to start when stepper_x's
        # rotation_distance exceeds this (a stand-in for any config Klipper rejects).
        limit = config.getfloat('reject_rotation_distance_above', None)
        if limit is not None:
            rd = config.getsection('stepper_x').getfloat('rotation_distance')
            if rd > limit:
                raise config.error(
                    "klipcal_bench: stepper_x rotation_distance %.6f is above"
                    " reject_rotation_distance_above %.6f" % (rd, limit))
        pheaters = self.printer.load_object(config, 'heaters')
        pheaters.add_sensor_factory(
            'klipcal_file', lambda cfg: FileTemperatureSensor(cfg, self))
        gcode = self.printer.lookup_object('gcode')
        gcode.register_command('BENCH_SLEEP', self.cmd_BENCH_SLEEP,
                               desc=self.cmd_BENCH_SLEEP_help)
        # Batch mode (-i FILE) has no terminal for G-code responses: log them
        # so `bench.py batch` can report klippy's own error lines ("!! ...").
        if self.printer.get_start_args().get('debuginput'):
            gcode.register_output_handler(self._log_response)

    def _log_response(self, msg):
        for line in msg.split('\n'):
            logging.info("klipcal_bench response: %s", line)

    def _forget_interrupted(self):
        self.interrupted = None

    def read_time(self, eventtime):
        """Reading timestamp: real seconds since this module loaded."""
        return eventtime - self.t0

    cmd_BENCH_SLEEP_help = ("Sleep SECONDS of real time (lets a bench print"
                            " last); a pause interrupts it and RESUME sleeps"
                            " the rest")

    def cmd_BENCH_SLEEP(self, gcmd):
        # The G-code mutex is released while sleeping, so other G-code (PAUSE,
        # CANCEL_PRINT, scripts sent through Moonraker) runs meanwhile, as it
        # would between the lines of a real print. When
        # virtual_sdcard is asked to pause, the sleep stops and the file is
        # rewound to this line, so RESUME sleeps the remaining time.
        seconds = gcmd.get_float('SECONDS', minval=0., maxval=3600.)
        sdcard = self.printer.lookup_object('virtual_sdcard', None)
        from_sd = sdcard is not None and sdcard.is_cmd_from_sd()
        key = None
        if from_sd:
            key = (id(sdcard.current_file), sdcard.file_position)
            if self.interrupted is not None and self.interrupted[0] == key:
                seconds = self.interrupted[1]
            self.interrupted = None
        mutex = self.printer.lookup_object('gcode').get_mutex()
        held = mutex.test()
        if held:
            mutex.unlock()
        try:
            end = self.reactor.monotonic() + seconds
            while True:
                now = self.reactor.monotonic()
                if now >= end:
                    break
                if from_sd and sdcard.must_pause_work:
                    self.interrupted = (key, end - now)
                    sdcard.next_file_position = sdcard.file_position
                    break
                self.reactor.pause(min(end, now + 0.1))
        finally:
            if held:
                mutex.lock()


def load_config(config):
    return KlipcalBench(config)
