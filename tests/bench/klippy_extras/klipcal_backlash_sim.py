# klipcal_backlash_sim: the bench's simulated mechanical backlash. Tests only.
#
#   [klipcal_backlash_sim]
#   state_file: /abs/comms/nozzle_true.json
#   x: 0.08   # mm of play per joint: cartesian x, y, z; corexy a, b, z
#   x1: 0.03  # with [dual_carriage] (axis x): the second carriage's X play
#
# Each joint (axis, or CoreXY motor A = X+Y, B = X-Y) has a play operator of
# width b: the nozzle stays put until the motor has taken up the play, so
# after travel in + the nozzle lags the motor by b/2, after travel in - it
# leads by b/2. The motor position is the toolhead's commanded position
# (including [backlash]'s shifted end points); [backlash_compensation]'s
# stepper pre-tension is modelled as the motor running on by c/2 in the
# direction of travel and returning. Homing resets each joint as after travel
# in -. After every move the true nozzle position is written to state_file
# (a JSON object), which only tests read: it is what a person sees through
# the nozzle camera, with the carriage it belongs to. Selecting the other
# dual carriage re-seats the joint (set_position) as homing does. Must not
# touch anything Klipper reports.
#
# This file may be distributed under the terms of the GNU GPLv3 license.
import json
import os


class BacklashSim:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.path = config.get('state_file')
        pcfg = config.getsection('printer')
        self.corexy = pcfg.get('kinematics') == 'corexy'
        names = ('a', 'b', 'z') if self.corexy else ('x', 'y', 'z')
        self.names = names
        self.play = [config.getfloat(n, 0.0, minval=0.0) for n in names]
        self.play_x1 = config.getfloat('x1', 0.0, minval=0.0)
        self.carriage = 0
        self.motor = [0.0, 0.0, 0.0]
        self.nozzle = [0.0, 0.0, 0.0]  # joint space
        self.moves = 0
        self.printer.register_event_handler("klippy:connect", self._connect)

    def _connect(self):
        th = self.printer.lookup_object('toolhead')
        orig_move, orig_set = th.move, th.set_position

        def move(newpos, speed):
            start = list(th.get_position())
            orig_move(newpos, speed)
            self._moved(start, list(th.get_position()))

        def set_position(newpos, homing_axes=()):
            orig_set(newpos, homing_axes)
            self._reset(newpos)
        th.move, th.set_position = move, set_position
        self._reset(th.get_position())

    def _joints(self, pos):
        if self.corexy:
            return [pos[0] + pos[1], pos[0] - pos[1], pos[2]]
        return [pos[0], pos[1], pos[2]]

    def _cartesian(self, j):
        if self.corexy:
            return [(j[0] + j[1]) / 2.0, (j[0] - j[1]) / 2.0, j[2]]
        return list(j)

    def _comp_joints(self, dirs_xyz):
        """Joint offsets [backlash_compensation] pre-tensions by."""
        bc = self.printer.lookup_object('backlash_compensation', None)
        if bc is None:
            return [0.0, 0.0, 0.0]
        vals = bc.compensation_for()
        off = [0.5 * vals[a] * d for a, d in zip('xyz', dirs_xyz)]
        return self._joints(off)

    def _active_carriage(self):
        dc = self.printer.lookup_object('dual_carriage', None)
        if dc is None:
            return 0
        for i, c in enumerate(dc.get_rails()):
            if c.is_active():
                return i
        return 0

    def _plays(self):
        if self.carriage == 1 and not self.corexy:
            return [self.play_x1] + self.play[1:]
        return self.play

    def _take(self, i, m):
        h = 0.5 * self._plays()[i]
        self.nozzle[i] = min(max(self.nozzle[i], m - h), m + h)
        self.motor[i] = m

    def _reset(self, pos):
        self.carriage = self._active_carriage()
        self.motor = self._joints(pos)
        self.nozzle = [m + 0.5 * b for m, b in zip(self.motor, self._plays())]
        self._write()

    def _moved(self, start, end):
        dirs = [0 if e == s else (1 if e > s else -1)
                for s, e in zip(start[:3], end[:3])]
        comp = self._comp_joints(dirs)
        target = self._joints(end)
        for i in range(3):
            if comp[i]:
                self._take(i, target[i] + comp[i])
            self._take(i, target[i])
        self.moves += 1
        self._write()

    def _write(self):
        xyz = self._cartesian(self.nozzle)
        state = {'nozzle': xyz, 'commanded': self._cartesian(self.motor),
                 'joints': list(self.names), 'play_mm': self._plays(),
                 'carriage': self.carriage, 'moves': self.moves}
        tmp = self.path + '.tmp'
        with open(tmp, 'w') as f:
            json.dump(state, f)
        os.replace(tmp, self.path)


def load_config(config):
    return BacklashSim(config)
