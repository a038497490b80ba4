# backlash_compensation: klipcal bench stand-in for the backlash compensation
# module of Klipper PR 7259 (dmbutyugin's branch, the one the forum thread in
# shared/seeds/004 describes). It copies that module's INTERFACE only:
#
#   [backlash_compensation]
#   x_backlash: 0.0     # mm, >= 0 (also y_backlash, z_backlash)
#   smooth_time: 0.005  # s, > 0 and <= 0.1
#
#   SET_BACKLASH_COMPENSATION [X_BACKLASH=] [Y_BACKLASH=] [Z_BACKLASH=]
#                             [SMOOTH_TIME=]   (SMOOTH_TIME 0..0.1 at run time)
#   reply: "x_backlash:<v> y_backlash:<v> z_backlash:<v> smooth_time:<%.6f>"
#
# No status object (no get_status): only the reply and the config show the
# values. With a [dual_carriage], non-zero config values are refused at
# connect, and SET_BACKLASH_COMPENSATION sets the active carriage's values
# (the seed's [delayed_gcode] recipe switches carriages around it).
#
# It does not shape any step: the bench's mechanics (klipcal_backlash_sim)
# ask compensation_for() what the stepper would add, and apply it to the
# simulated play. Must not be used on a real printer.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
AXES = ('x', 'y', 'z')


class BenchBacklashCompensation:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.values = {a: config.getfloat(a + '_backlash', 0.0, minval=0.0)
                       for a in AXES}
        self.smooth_time = config.getfloat('smooth_time', 0.005,
                                           above=0.0, maxval=0.1)
        # Per dual carriage (None = the only one): axis -> mm.
        self.per_carriage = {}
        self.printer.register_event_handler("klippy:connect", self._connect)
        gcode = self.printer.lookup_object('gcode')
        gcode.register_command("SET_BACKLASH_COMPENSATION",
                               self.cmd_SET_BACKLASH_COMPENSATION,
                               desc=self.cmd_SET_BACKLASH_COMPENSATION_help)

    def _connect(self):
        if self.printer.lookup_object('dual_carriage', None) is not None:
            if any(v > 0. for v in self.values.values()):
                raise self.printer.config_error(
                    'Backlash compensation parameters cannot be'
                    ' configured via [backlash_compensation] section'
                    ' with dual_carriage(s)  enabled. Refer to Klipper'
                    ' documentation on how to configure backlash '
                    ' compensation for dual_carriage(s).')

    def _carriage(self):
        dc = self.printer.lookup_object('dual_carriage', None)
        if dc is None:
            return None
        for i, c in enumerate(dc.get_rails()):
            if c.is_active():
                return i
        return None

    def compensation_for(self):
        """Axis -> mm the steppers currently add (for the bench mechanics)."""
        key = self._carriage()
        if key is None:
            return dict(self.values)
        vals = dict(self.values)
        vals.update(self.per_carriage.get(key, {}))
        return vals

    cmd_SET_BACKLASH_COMPENSATION_help = "Set backlash compensation parameters"

    def cmd_SET_BACKLASH_COMPENSATION(self, gcmd):
        if gcmd.get_command_parameters():
            self.smooth_time = gcmd.get_float('SMOOTH_TIME', self.smooth_time,
                                              minval=0.0, maxval=0.1)
            current = self.compensation_for()
            new = {a: gcmd.get_float(a.upper() + '_BACKLASH', current[a],
                                     minval=0.0) for a in AXES}
            key = self._carriage()
            if key is None:
                self.values = new
            else:
                self.per_carriage[key] = new
        vals = self.compensation_for()
        gcmd.respond_info(' '.join('%s_backlash:%s' % (a, vals[a])
                                   for a in AXES)
                          + ' smooth_time:%.6f' % self.smooth_time)


def load_config(config):
    return BenchBacklashCompensation(config)
