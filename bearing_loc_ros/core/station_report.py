"""A station's input and output counters and its periodic status report (no ROS).

The station node counts readings received per input, bearings published and inputs
rejected per reason; every diagnostics period :meth:`StationCounters.report` summarises
them, and what changed since the previous report, as a level (``'ok'`` or ``'warn'``), a
one-line message and key/value pairs (``/diagnostics`` values). Stamps are integer ns.
"""

from collections import Counter

from .conventions import stamp_text


class StationCounters:
    """Counters of one station: ``received`` (input -> readings), ``rejected`` (reason ->
    inputs), ``published`` (bearings) and ``last_stamp_ns`` (stamp of the last published
    bearing, ns, or None)."""

    def __init__(self):
        self.published = 0
        self.rejected = Counter()
        self.received = Counter()
        self.last_stamp_ns = None
        self._rejected_reported = 0
        self._published_reported = 0
        self._udp_drops_reported = 0

    def count_published(self, stamp_ns):
        """One bearing stamped ``stamp_ns`` (ns) was published."""
        self.published += 1
        self.last_stamp_ns = stamp_ns

    def report(self, values, extra=None, receiver=None, udp_drops=None):
        """(level, message, values) of a status report: WARN when inputs were rejected or
        UDP datagrams dropped by the kernel (``udp_drops``: the socket's total, or None)
        since the previous report, or with a ``receiver`` problem (text); else OK.
        ``values`` (identity) come first, then the counters, then ``extra``."""
        total_rej = sum(self.rejected.values())
        new_rej = total_rej - self._rejected_reported
        new_pub = self.published - self._published_reported
        self._rejected_reported, self._published_reported = total_rej, self.published
        last = self.last_stamp_ns
        values = dict(values)
        values.update({
            'published': self.published,
            'published_since_last_report': new_pub,
            'rejected': total_rej,
            'last_stamp_ns': last if last is not None else '',
            'last_stamp_s': stamp_text(last) if last is not None else '',
        })
        values.update({f'received_{k}': v for k, v in sorted(self.received.items())})
        values.update({f'rejected_{k}': v for k, v in sorted(self.rejected.items())})
        values.update(extra or {})
        new_drops = 0
        if udp_drops is not None:
            new_drops, self._udp_drops_reported = (udp_drops - self._udp_drops_reported,
                                                   udp_drops)
        if new_rej or new_drops or receiver:
            message = '; '.join(
                ([receiver] if receiver else [])
                + ([f'{new_rej} input(s) rejected since last report'] if new_rej else [])
                + ([f'{new_drops} UDP datagram(s) dropped by the kernel (node busy or '
                    'receive buffer full) since last report'] if new_drops else []))
            return 'warn', message, values
        if self.published == 0:
            return 'ok', 'waiting for readings', values
        return 'ok', f'{new_pub} bearing(s) published since last report', values
