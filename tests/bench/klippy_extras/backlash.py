# backlash: klipcal bench stand-in for the [backlash] module of Klipper
# PR 7157 (the "other branch" of shared/seeds/004). It copies that module's
# INTERFACE only:
#
#   [backlash]
#   kinematics: cartesian   # or corexy (default cartesian)
#   x: 0.0                  # mm (cartesian: x, y, z; corexy: a, b, z)
#
# No G-code command and no status object. It shifts the end point of each
# move by the axis (or, on corexy, motor A = X+Y / B = X-Y) backlash while
# that axis last moved in + (tracking starts once the axis is homed), and
# hides the shift from the toolhead's reported position.
#
# This file may be distributed under the terms of the GNU GPLv3 license.


class BenchBacklash:
    def __init__(self, config):
        self.printer = config.get_printer()
        kin = config.get('kinematics', 'cartesian')
        if kin not in ('cartesian', 'corexy'):
            raise config.error("Unknown backlash kinematics '%s'. "
                               "Must be 'cartesian' or 'corexy'." % (kin,))
        self.corexy = kin == 'corexy'
        names = ('a', 'b', 'z') if self.corexy else ('x', 'y', 'z')
        self.names = names
        self.values = [config.getfloat(n, 0.0) for n in names]
        # Per joint: 0 unknown (not homed), 1 last moved +, -1 last moved -.
        self.dirs = [0, 0, 0]
        self.next_transform = None
        self.toolhead = None
        self.printer.register_event_handler("klippy:connect", self._connect)
        self.printer.register_event_handler("homing:home_rails_end",
                                            self._homed)

    def _connect(self):
        self.toolhead = self.printer.lookup_object('toolhead')
        gcode_move = self.printer.lookup_object('gcode_move')
        self.next_transform = gcode_move.set_move_transform(self, force=True)
        orig = self.toolhead.get_status

        def status(eventtime):
            res = orig(eventtime)
            off = self._offset()
            if any(off):
                pos = list(self.toolhead.get_position())
                for i in range(3):
                    pos[i] -= off[i]
                res['position'] = self.toolhead.Coord(*pos)
            return res
        self.toolhead.get_status = status

    def _homed(self, homing_state, rails):
        axes = homing_state.get_axes()
        if self.corexy:
            if 0 in axes or 1 in axes:
                self.dirs[0] = self.dirs[1] = -1
        else:
            for i in (0, 1):
                if i in axes:
                    self.dirs[i] = -1
        if 2 in axes:
            self.dirs[2] = -1

    def _joints(self, pos):
        if self.corexy:
            return [pos[0] + pos[1], pos[0] - pos[1], pos[2]]
        return [pos[0], pos[1], pos[2]]

    def _offset(self):
        j = [v if d == 1 else 0.0 for v, d in zip(self.values, self.dirs)]
        if self.corexy:
            return [(j[0] + j[1]) / 2.0, (j[0] - j[1]) / 2.0, j[2]]
        return j

    def get_position(self):
        pos = list(self.next_transform.get_position())
        off = self._offset()
        for i in range(3):
            pos[i] -= off[i]
        return pos

    def move(self, newpos, speed):
        start = self._joints(self.get_position())
        end = self._joints(newpos)
        for i in range(3):
            d = end[i] - start[i]
            if d != 0.0 and self.dirs[i] != 0:
                self.dirs[i] = 1 if d > 0 else -1
        off = self._offset()
        adjusted = list(newpos)
        for i in range(3):
            adjusted[i] += off[i]
        self.next_transform.move(adjusted, speed)


def load_config(config):
    return BenchBacklash(config)
