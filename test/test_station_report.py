"""core.station_report: a station's counters and its status report, without ROS."""

from bearing_loc_ros.core.station_report import StationCounters


def test_report_warns_once_per_new_rejection_and_counts_deltas():
    c = StationCounters()
    level, message, values = c.report({'station': 's1'})
    assert (level, message) == ('ok', 'waiting for readings')
    assert values['last_stamp_ns'] == '' and values['published'] == 0
    c.received['udp'] += 3
    c.count_published(12 * 10 ** 9 + 5)
    c.rejected['bad_azimuth'] += 2
    level, message, values = c.report({'station': 's1'}, {'extra': 1})
    assert level == 'warn' and message == '2 input(s) rejected since last report'
    assert list(values)[:4] == ['station', 'published', 'published_since_last_report',
                                'rejected']
    assert values['last_stamp_s'] == '12.000000005' and values['received_udp'] == 3
    assert values['rejected_bad_azimuth'] == 2 and list(values)[-1] == 'extra'
    level, message, values = c.report({})          # nothing new: OK again
    assert (level, message) == ('ok', '0 bearing(s) published since last report')
    assert values['published_since_last_report'] == 0


def test_report_warns_on_new_kernel_drops_and_receiver_problems():
    c = StationCounters()
    c.count_published(1)
    assert c.report({}, udp_drops=4)[:2] == (
        'warn', '4 UDP datagram(s) dropped by the kernel (node busy or receive buffer full) '
        'since last report')
    assert c.report({}, udp_drops=4)[0] == 'ok'      # the total did not grow
    level, message, _ = c.report({}, receiver='receiver unreachable (timeout)', udp_drops=6)
    assert level == 'warn' and message.startswith('receiver unreachable (timeout); 2 UDP')
