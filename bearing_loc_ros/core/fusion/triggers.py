"""Epoch triggers: when the multi-station pipeline computes an epoch, and for which time.

* ``event``: an epoch is *pending* from the first bearing newer than the previous epoch
  (arrival time t_open on the node clock); it closes, with the stations that reported
  (the *pending* stations: newest stamp after the previous epoch), as soon as

  1. every expected station (the live ones, plus configured ones added less than
     ``station_timeout`` ago that have not reported yet) has reported: epoch time t = the
     oldest of the expected stations' newest stamps; or
  2. now >= t_open + ``max_latency`` with at least ``min_stations`` pending stations: a
     station whose bearing was lost is not waited for; or
  3. a pending station reports again (a new observation cycle began) with at least
     ``min_stations`` pending stations: the bearing of the station that was lost will not
     come.

  In cases 2 and 3, t = the oldest of the pending stations' stamps of this cycle (for a
  station that reported again, its previous stamp). On a link that loses bearings, an
  epoch is thus fixed whenever two or more stations' bearings of a cycle arrive.
* ``timer``: at each tick ``now``, every grid time t_k = k · period (period = 1 / rate,
  integer ns) with t_k <= now − max_latency not yet processed; after a gap, at most
  buffer_age / period of them (older epochs would find their bearings pruned). Lost
  bearings only leave their station out of that epoch.

All times are integer ns on the node clock.
"""


def event_epoch_time(registry, now):
    """The event-trigger epoch time at ``now`` (ns), or None when no epoch is due."""
    last = registry.last_epoch_ns
    expected = registry.expected_stations(now)
    t = None
    complete = bool(expected)
    for s in expected:
        n = registry.buffer(s).newest_stamp_ns
        if n is None or (last is not None and n <= last):
            complete = False
            break
        t = n if t is None or n < t else t
    if complete:
        return t
    opened = registry.open_since_ns
    repeat = registry.repeat_stamp_ns
    if opened is None or (repeat is None and now < opened + registry.max_latency_ns):
        return None
    pending, t = 0, repeat
    for s in registry.live_stations():
        n = registry.buffer(s).newest_stamp_ns
        if n is not None and (last is None or n > last):
            pending += 1
            t = n if t is None or n < t else t
    if pending < registry.config.min_stations:
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
