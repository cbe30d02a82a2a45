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

  In cases 2 and 3, t = the oldest stamp after the previous epoch of a live station at
  which ``min_stations`` stations have a bearing within ``sync_tolerance``
  (:func:`closable_time`; in case 3 no later than the repeating station's previous stamp);
  a cycle of which a single bearing arrived is passed over. On a link that loses bearings,
  an epoch is thus fixed whenever two or more stations' bearings of a cycle arrive.
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
    # The scan starts at the station that was missing at the previous call: with the
    # bearings of a cycle arriving one station after the other, each call then looks at one
    # or two stations instead of all those before (O(N) per epoch, not O(N²)). Whether all
    # expected stations reported, and the oldest newest stamp t when they have, do not
    # depend on the order of the scan.
    k = 0
    if registry.event_blocker is not None:
        try:
            k = expected.index(registry.event_blocker)
        except ValueError:
            k = 0
    for s in (expected[k:] + expected[:k]) if k else expected:
        n = registry.buffer(s).newest_stamp_ns
        if n is None or (last is not None and n <= last):
            complete = False
            registry.event_blocker = s
            break
        t = n if t is None or n < t else t
    if complete:
        return t
    opened = registry.open_since_ns
    repeat = registry.repeat_stamp_ns
    deadline = opened is not None and now >= opened + registry.max_latency_ns
    if opened is None or (repeat is None and not deadline):
        return None
    return closable_time(registry, last, None if deadline else repeat)


def closable_time(registry, last, limit=None):
    """The oldest time t (ns) among the live stations' stamps after ``last`` (the
    previous epoch; None: any), t <= ``limit`` when given, at which at least
    ``min_stations`` stations have a bearing after ``last`` within sync_tolerance of t;
    None when there is none. A cycle of which only one bearing arrived is passed over."""
    tol = registry.align.sync_tolerance_ns
    after = last if last is not None else -2 ** 63
    bufs = [registry.buffer(s) for s in registry.live_stations()]
    stamps = sorted({b.stamp_ns for buf in bufs if (buf.newest_stamp_ns or after) > after
                     for b in buf.bearings if b.stamp_ns > after})
    need = registry.config.min_stations
    for t in stamps:
        if limit is not None and t > limit:
            break
        n = 0
        for buf in bufs:
            if buf.nearest(t, tol, after_ns=after) is not None:
                n += 1
                if n >= need:
                    return t
    return None


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
