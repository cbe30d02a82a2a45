"""Epoch triggers: when the multi-station pipeline computes an epoch, and for which time.

* ``event``: an epoch as soon as every expected station (the live ones, plus those added
  less than ``station_timeout`` ago that have not reported yet) has a bearing newer than
  the previous epoch; epoch time t = the oldest of those stations' newest stamps.
* ``timer``: at each tick ``now``, every grid time t_k = k · period (period = 1 / rate,
  integer ns) with t_k <= now − max_latency not yet processed; after a gap, at most
  buffer_age / period of them (older epochs would find their bearings pruned).

All times are integer ns on the node clock.
"""


def event_epoch_time(registry, now):
    """The event-trigger epoch time at ``now`` (ns), or None when no epoch is due."""
    expected = registry.expected_stations(now)
    if not expected:
        return None
    t = None
    for s in expected:
        n = registry.buffer(s).newest_stamp_ns
        if n is None:
            return None
        t = n if t is None or n < t else t
    last = registry.last_epoch_ns
    if last is not None and t <= last:
        return None
    return t


def timer_epoch_times(now, period_ns, max_latency_ns, last_epoch_ns, buffer_age_ns):
    """Grid times t_k = k · period_ns (ns) due at ``now``: t_k <= now − max_latency_ns,
    after ``last_epoch_ns`` (the first tick processes only the newest due one), at most
    max(1, buffer_age_ns // period_ns) of them."""
    target = now - max_latency_ns
    if target < 0:
        return range(0)
    k_last = target // period_ns
    if last_epoch_ns is None:
        k_first = k_last
    else:
        k_first = last_epoch_ns // period_ns + 1
        backfill = max(1, buffer_age_ns // period_ns)
        k_first = max(k_first, k_last - backfill + 1)
    return range(k_first * period_ns, (k_last + 1) * period_ns, period_ns)
