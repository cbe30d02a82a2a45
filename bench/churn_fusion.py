"""Publisher churn under discovery: fix continuity and the fusion node's RSS.

    .venv/bin/python bench/churn_fusion.py [--rounds 3] [--ghosts 200] [--stations 4]

Starts a fusion node (``bearing_loc_ros.fusion_node``, ``discover:=true``, default
QoS and trigger, estimator ls) in namespace /soak, fed by ``--stations`` stations at 10 Hz
(the publisher of ``soak_fusion.py``), all on loopback with their own ROS_DOMAIN_ID. After a
warm-up, each round starts a process holding ``--ghosts`` empty publishers on
``/soak/ghost_<k>/bearing``, waits until the node has found all of them (its
/diagnostics ``discovery_candidates``, the topics its discovery probe process watches; with
``--no-probe``, ``discovered_stations``, the topics it subscribed to itself), holds them for
``--hold`` s, ends the process and waits until the node has dropped them again and
``--settle`` s more. Prints the node's RSS (/proc/<pid>/status VmRSS; with the probe, the
probe process's RSS too) before the churn, with the ghosts and after each round, and the
fixes: the largest gap between consecutive fix stamps (one epoch period = no outage) and the
fixes per observation cycle while the ghosts came and went. ``--node-log PATH`` keeps the node's
output, with its debug messages (the heap trims of ``bearing_loc_ros.memory``).

``--env NAME=VALUE`` (repeatable) sets an environment variable of the fusion node only, for
example ``--env MALLOC_ARENA_MAX=2``; ``--no-trim`` runs the node without its heap trim;
``--no-probe`` with ``discovery_probe:=false`` (the node subscribes to every discovered
topic itself).
"""
import argparse
import os
import subprocess
import sys
import time

GHOSTS = '''
import sys, rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
rclpy.init()
node = rclpy.create_node('churn', namespace='/soak')
pubs = [node.create_publisher(PoseWithCovarianceStamped, f'ghost_{k}/bearing', 10)
        for k in range(int(sys.argv[1]))]
print('ready', flush=True)
sys.stdin.readline()
node.destroy_node()
rclpy.try_shutdown()
'''

RUN = 'from bearing_loc_ros.fusion_node import main; main()'
NO_TRIM = 'import bearing_loc_ros.memory as m; m.HEAP.trim = None; ' + RUN


def rss_kb(pid):
    with open(f'/proc/{pid}/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1])
    return None


def children(pid):
    """Process ids of ``pid``'s children (Linux /proc)."""
    out = []
    try:
        for task in os.listdir(f'/proc/{pid}/task'):
            with open(f'/proc/{pid}/task/{task}/children') as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


def probe_rss_kb(pid):
    """Summed RSS of ``pid``'s children (the discovery probe), in KiB."""
    total = 0
    for c in children(pid):
        try:
            total += rss_kb(c) or 0
        except OSError:
            pass
    return total


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--stations', type=int, default=4)
    ap.add_argument('--rate', type=float, default=10.0)
    ap.add_argument('--ghosts', type=int, default=200)
    ap.add_argument('--rounds', type=int, default=3)
    ap.add_argument('--hold', type=float, default=5.0, help='seconds with the ghosts present')
    ap.add_argument('--settle', type=float, default=5.0, help='seconds after they left')
    ap.add_argument('--warm-up', type=float, default=15.0)
    ap.add_argument('--env', action='append', default=[], help='NAME=VALUE for the node')
    ap.add_argument('--node-log', help='file for the fusion node output (debug level)')
    ap.add_argument('--no-trim', action='store_true',
                    help='the node without its heap trim (bearing_loc_ros.memory), to compare')
    ap.add_argument('--no-probe', action='store_true',
                    help='discovery_probe:=false: the node subscribes to every discovered topic')
    a = ap.parse_args(argv)
    here = os.path.dirname(os.path.abspath(__file__))
    repo = os.path.dirname(here)
    sys.path.insert(0, here)
    from soak_fusion import bench_env, start_publisher
    env = bench_env(160, 40)
    node_env = dict(env, **dict(kv.split('=', 1) for kv in a.env))
    names = [f's{k + 1}' for k in range(a.stations)]
    fusion = subprocess.Popen(
        [sys.executable, '-c', NO_TRIM if a.no_trim else RUN, '--ros-args', '-r', '__ns:=/soak',
         '-p', f'stations:=[{",".join(names)}]', '-p', 'estimator:=ls',
         '-p', 'discover:=true', '-p', 'accuracy_map.enabled:=false',
         '-p', 'diagnostics_period:=0.5',
         '-p', f'discovery_probe:={"false" if a.no_probe else "true"}']
        + (['--log-level', 'soak.fusion:=debug'] if a.node_log else []),
        cwd=repo, env=node_env, stderr=subprocess.STDOUT,
        stdout=open(a.node_log, 'w') if a.node_log else subprocess.DEVNULL)
    total = a.warm_up + a.rounds * (a.hold + a.settle + 60) + 30
    pub = start_publisher(env, a.stations, a.rate, total)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from bearing_loc_ros.processes import interrupt
    rclpy.init()
    node = rclpy.create_node('churn_probe')
    diag, stamps = {}, []

    def on_diag(msg):
        for s in msg.status:
            if s.name.endswith(': fusion'):
                diag.update({kv.key: kv.value for kv in s.values})

    def on_fix(msg):
        stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    node.create_subscription(PoseWithCovarianceStamped, '/soak/fix', on_fix, 100)

    def spin(seconds, until=None):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
            if until is not None and until():
                return True
        return until is None

    key = 'discovered_stations' if a.no_probe else 'discovery_candidates'

    def discovered():
        return int(diag.get(key, -1))

    ghosts = []
    try:
        spin(a.warm_up)
        r0 = rss_kb(fusion.pid)
        print(f'warm-up done: RSS {r0 / 1024:.1f} MiB, fixes {diag.get("fixes")}, '
              f'discovered {discovered()}', flush=True)
        k0 = len(stamps)
        t0 = time.monotonic()
        for r in range(a.rounds):
            g = subprocess.Popen([sys.executable, '-c', GHOSTS, str(a.ghosts)], cwd=repo,
                                 env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                 text=True)
            ghosts.append(g)
            assert g.stdout.readline().strip() == 'ready'
            found = spin(120, lambda: discovered() >= a.ghosts)
            spin(a.hold)
            r_with = rss_kb(fusion.pid)
            p_with = probe_rss_kb(fusion.pid)
            g.stdin.close()
            g.wait(timeout=30)
            left = spin(120, lambda: discovered() == 0)
            spin(a.settle)
            r_after = rss_kb(fusion.pid)
            print(f'round {r + 1}: {a.ghosts} ghosts {"discovered" if found else "NOT all"} '
                  f'{"and dropped" if left else "NOT dropped"}; RSS with them '
                  f'{r_with / 1024:.1f} MiB ({100 * (r_with - r0) / r0:+.2f} %), after '
                  f'{r_after / 1024:.1f} MiB ({100 * (r_after - r0) / r0:+.2f} %); probe '
                  f'process {p_with / 1024:.1f} MiB with them, {len(children(fusion.pid))} '
                  f'running after', flush=True)
        t1 = time.monotonic()
        s = sorted(set(stamps[k0:]))
        gaps = [b - c for b, c in zip(s[1:], s)]
        cycles = (t1 - t0) * a.rate
        print(f'fixes during the churn: {len(s)} of {cycles:.0f} observation cycles '
              f'({100 * len(s) / cycles:.2f} %); largest gap between fix stamps '
              f'{max(gaps, default=float("nan")):.3f} s (epoch period {1 / a.rate:.3f} s); '
              f'gaps > 1.5 periods: {sum(x > 1.5 / a.rate for x in gaps)}')
        print(f'RSS {r0 / 1024:.1f} -> {r_after / 1024:.1f} MiB after the last round: '
              f'{100 * (r_after - r0) / r0:+.2f} %; diagnostics: ' + ', '.join(
                  f'{k}={v}' for k, v in diag.items() if k.startswith('discovery')))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for g in ghosts:
            if g.poll() is None:
                g.kill()
                g.wait()
        for p in (pub, fusion):
            if p.poll() is None:
                interrupt(p, 10)


if __name__ == '__main__':
    main()
