# klipcal_idle: lets Klipper's own [idle_timeout] fire on the bench.
#
# In file-output mode the MCU clock never advances (estimated_print_time is
# always 0), so the toolhead never looks caught up with its queue and
# idle_timeout stays "Printing" forever: its timeout (TURN_OFF_HEATERS, M84)
# can never fire. With a bare [klipcal_idle] section the toolhead reports its
# queue done at the moment it last changed (in this mode every move is done
# when it is queued), so idle_timeout goes "Ready" half a second later and
# turns the heaters off once its timeout has passed with nothing queued, as on
# a real printer. idle_timeout.py itself is not touched. Opt-in: printers
# without the section behave as before (idle_timeout never fires).
#
# This file may be distributed under the terms of the GNU GPLv3 license.


class KlipcalIdle:
    def __init__(self, config):
        self.printer = config.get_printer()
        self.reactor = self.printer.get_reactor()
        self.toolhead = None
        self.print_time = None
        self.since = 0.
        self.printer.register_event_handler("klippy:connect", self._connect)

    def _connect(self):
        self.toolhead = self.printer.lookup_object('toolhead')
        inner = self.toolhead.check_busy

        def check_busy(eventtime):
            print_time, est_print_time, lookahead_empty = inner(eventtime)
            self._sample(eventtime)
            done = print_time + (eventtime - self.since)
            return print_time, max(est_print_time, done), lookahead_empty

        self.toolhead.check_busy = check_busy
        # The queue's last change is noted at 4 Hz, not only when idle_timeout
        # looks, so the timeout counts from the last command, not from its
        # own previous check.
        self.reactor.register_timer(self._tick, self.reactor.NOW)

    def _sample(self, eventtime):
        if self.toolhead.print_time != self.print_time:
            self.print_time = self.toolhead.print_time
            self.since = eventtime

    def _tick(self, eventtime):
        self._sample(eventtime)
        return eventtime + 0.25


def load_config(config):
    return KlipcalIdle(config)
