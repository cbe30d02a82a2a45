"""``make demo``: simulator -> fusion node over DDS on ``seed000``, checked against truth.

Runs ``simulator_node`` on the scenario of Wang, Zhang & Wu (2006), section 4 (three stations, a
target at ~60 km moving at (−150, −1000, 0) m/s, σ = 3 mrad, a bearing every 2 s) and
``fusion_node`` (use_sim_time) as separate processes, faster than real time; an in-demo subscriber
records ``fix`` and ``truth`` (the bearings for the plot come from the same seeded core
simulation). It prints one line per fix (time, error to truth, predicted 1σ), a summary comparing
the RMS error with the Cramér-Rao bound evaluated along the true track
(core/crlb.py) and writes a PNG (stations, bearing rays, true track, fixes with 1σ error
ellipses) to ``demo_out/``. Children are stopped with SIGINT, then SIGTERM, then SIGKILL, and
always reaped, also on errors and Ctrl-C. Exit code 0 on success, 1 on failure, 130 on Ctrl-C.

Usage: ``python -m bearing_loc_ros.demo [--duration 30] [--time-scale 8] [--seed 0]
[--estimator mle] [--out demo_out] [--domain-id N]``.
"""

import argparse
import math
import os
import signal
import sys
import time

import numpy as np

from .processes import ChildProcess

NS_PER_S = 1_000_000_000


def parse_args(argv):
    """Parse and range-check the demo's command line (durations in s)."""
    ap = argparse.ArgumentParser(prog='python -m bearing_loc_ros.demo',
                                 description=__doc__.splitlines()[0])
    ap.add_argument('--duration', type=float, default=30.0, help='simulated seconds (30)')
    ap.add_argument('--time-scale', type=float, default=8.0,
                    help='simulated seconds per wall second (8)')
    ap.add_argument('--seed', type=int, default=0, help='simulation seed (0)')
    from .core.registry import default_estimator
    ap.add_argument('--estimator', default=default_estimator(),
                    help=f'fusion estimator (default {default_estimator()})')
    ap.add_argument('--out', default='demo_out', help='output directory (demo_out)')
    ap.add_argument('--domain-id', type=int, default=None,
                    help='ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID, else derived from the pid)')
    args = ap.parse_args(argv)
    if not (0 < args.duration <= 600 and 0 < args.time_scale <= 1000):
        ap.error('--duration must be in (0, 600] and --time-scale in (0, 1000]')
    if args.domain_id is not None and not 0 <= args.domain_id <= 101:
        ap.error('--domain-id must be in [0, 101]')
    return args


def child_env(domain_id):
    """Environment of the node processes: ROS_DOMAIN_ID, loopback discovery, unbuffered."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('AMENT_PREFIX_PATH', sys.prefix)
    env['PYTHONUNBUFFERED'] = '1'
    return env


def write_png(path, sc, fixes, truth_track, bearings, stats, x_true, t_fix):
    """Overview (km): stations, bearing rays, true track, fixes; target plot (m): each fix
    minus the truth at its time with its 1σ error ellipse; error vs time with the predicted
    1σ and the CRLB."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from .core.gis import ellipse_ring_enu, sigma_probability

    fig = plt.figure(figsize=(13, 7), dpi=100)
    grid = fig.add_gridspec(2, 2, width_ratios=(1.35, 1.0))
    ax = fig.add_subplot(grid[:, 0])
    zoom = fig.add_subplot(grid[0, 1])
    err = fig.add_subplot(grid[1, 1])
    km = 1e-3
    track = np.asarray(truth_track)
    for st, (pos, az, length) in bearings:
        end = pos[:2] + length * np.array([math.cos(az), math.sin(az)])
        ax.plot([pos[0] * km, end[0] * km], [pos[1] * km, end[1] * km], color='0.6', lw=0.5,
                alpha=0.5, zorder=1)
    if len(track):
        ax.plot(track[:, 0] * km, track[:, 1] * km, 'k-', lw=1.5, label='true track',
                zorder=2)
    xs = np.array([x for _, x, _ in fixes])
    ax.plot(xs[:, 0] * km, xs[:, 1] * km, 'o', color='tab:blue', ms=3, label='fixes', zorder=4)
    for s in sc.stations:
        p = s.trajectory.position(0.0)
        ax.plot(p[0] * km, p[1] * km, '^', color='tab:red', ms=9, zorder=5)
        ax.annotate(s.id, (p[0] * km, p[1] * km), textcoords='offset points', xytext=(5, 5))
    ax.plot([], [], '^', color='tab:red', label='stations')
    ax.plot([], [], color='0.6', lw=0.5, label='bearing rays')
    ax.set_xlabel('East (km)')
    ax.set_ylabel('North (km)')
    ax.set_aspect('equal', adjustable='datalim')
    ax.grid(True, alpha=0.3)
    ax.legend(loc='best', fontsize=8)
    ax.set_title(f'{sc.name}: {len(fixes)} fixes, RMSE {stats["rmse"]:.0f} m, '
                 f'CRLB {stats["crlb_rms"]:.0f} m (ratio {stats["ratio"]:.2f})', fontsize=10)

    # Target plot: every fix relative to the truth at its time, with its 1σ ellipse.
    one_sigma = sigma_probability(1.0)
    for k, (_, x, P) in enumerate(fixes):
        e = x[:2] - x_true[k][:2]
        try:
            ell = ellipse_ring_enu([e[0], e[1], 0.0], P, one_sigma, points=63)
            zoom.plot(ell[:, 0], ell[:, 1], color='tab:blue', lw=0.6, alpha=0.6)
        except ValueError:          # a fix without a usable horizontal covariance: no ellipse
            pass
        zoom.plot(e[0], e[1], 'o', color='tab:blue', ms=3)
    zoom.plot(0.0, 0.0, 'kx', ms=9, label='truth')
    zoom.plot([], [], color='tab:blue', label='fix − truth, 1σ ellipse (E-N marginal)')
    zoom.set_aspect('equal', adjustable='datalim')
    zoom.set_xlabel('East error (m)')
    zoom.set_ylabel('North error (m)')
    zoom.grid(True, alpha=0.3)
    zoom.legend(fontsize=7, loc='best')

    err.plot(t_fix, stats['error'], 'o-', ms=3, lw=0.8, label='|error| to truth')
    err.plot(t_fix, stats['predicted'], '--', label='predicted 1σ  sqrt(tr P)')
    err.plot(t_fix, stats['crlb'], '-', color='tab:red', label='CRLB  sqrt(tr CRLB)')
    err.set_xlabel('time (s)')
    err.set_ylabel('3D error (m)')
    err.grid(True, alpha=0.3)
    err.legend(fontsize=7, loc='best')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args):
    """Run the demo; return the exit code."""
    from .core.evaluation import track_crlb_statistics
    from .core.simulation import load_scenario, simulate
    from .scenarios import resolve_scenario

    os.makedirs(args.out, exist_ok=True)
    path = resolve_scenario('seed000.yaml')
    sc = load_scenario(path)
    domain = args.domain_id
    if domain is None:
        domain = int(os.environ.get('ROS_DOMAIN_ID') or 1 + os.getpid() % 100)
    env = child_env(domain)
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                                           'AMENT_PREFIX_PATH')})
    print(f'demo: scenario {path} ({len(sc.stations)} stations), {args.duration:g} s of '
          f'simulated time at x{args.time_scale:g}, estimator {args.estimator}, '
          f'ROS_DOMAIN_ID={domain}', flush=True)

    import rclpy
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from .ros_conversions import fix_from_msg, time_to_ns

    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    children = []
    ctx = rclpy.Context()
    # No rclpy signal handlers: Ctrl-C must raise KeyboardInterrupt here so the children are
    # stopped by the finally clause below.
    rclpy.init(context=ctx, args=[], signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('demo_listener', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    fixes, truth = [], {}
    printed = [0]
    # The bearings the simulator publishes are the core simulation's for this seed; the demo
    # takes them (for the rays of the PNG) from the core rather than subscribing, so the
    # fusion node is the only bearing subscriber and the simulator, which starts once every
    # bearing topic is matched, never starts before the fusion node is listening.
    bearings = [e.bearing for e in simulate(sc, duration=args.duration, seed=args.seed).bearings]

    def on_fix(msg):
        fixes.append(fix_from_msg(msg))

    def on_truth(msg):
        p = msg.pose.position
        truth[time_to_ns(msg.header.stamp)] = np.array([p.x, p.y, p.z])

    node.create_subscription(PoseWithCovarianceStamped, '/fix', on_fix, qos)
    node.create_subscription(PoseStamped, '/truth', on_truth, qos)

    def true_position(t_ns):
        """Truth sample at t (the /truth topic), else the scenario trajectory."""
        if t_ns in truth:
            return truth[t_ns]
        return np.asarray(sc.targets[0].trajectory.position((t_ns - sc.epoch_ns) / NS_PER_S))

    def print_new_fixes():
        while printed[0] < len(fixes):
            stamp, x, P = fixes[printed[0]]
            printed[0] += 1
            t = (stamp - sc.epoch_ns) / NS_PER_S
            err = np.linalg.norm(x - true_position(stamp))
            sigma = math.sqrt(np.trace(P))
            print(f'fix  t={t:6.1f} s  error {err:8.1f} m  predicted 1σ {sigma:8.1f} m  '
                  f'({x[0] / 1e3:7.2f}, {x[1] / 1e3:7.2f}, {x[2] / 1e3:5.2f}) km', flush=True)

    def spin(seconds, until=None):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
            print_new_fixes()
            if until is not None and until():
                return True
        return until() if until is not None else True

    py = sys.executable
    stations = '[' + ','.join(f'"{s.id}"' for s in sc.stations) + ']'
    code = 1
    try:
        fusion = ChildProcess([py, '-m', 'bearing_loc_ros.fusion_node', '--ros-args',
                               '-p', f'stations:={stations}', '-p', 'use_sim_time:=true',
                               '-p', f'estimator:={args.estimator}'],
                              env=env, log_path=os.path.join(args.out, 'fusion.log'),
                              name='fusion')
        children.append(fusion)
        if not spin(30.0, lambda: node.count_publishers('/fix') > 0 or not fusion.running()):
            raise RuntimeError('fusion_node did not come up')
        if not fusion.running():
            raise RuntimeError('fusion_node exited at start-up')
        sim = ChildProcess([py, '-m', 'bearing_loc_ros.simulator_node', '--ros-args',
                            '-p', f'scenario:={path}', '-p', f'seed:={args.seed}',
                            '-p', f'time_scale:={args.time_scale}',
                            '-p', f'duration:={args.duration}',
                            '-p', 'start_delay:=15.0'],
                           env=env, log_path=os.path.join(args.out, 'simulator.log'),
                           name='simulator')
        children.append(sim)
        budget = 15.0 + args.duration / args.time_scale + 30.0
        if not spin(budget, lambda: not sim.running()):
            raise RuntimeError(f'simulator did not finish within {budget:.0f} s')
        if sim.proc.returncode != 0:
            raise RuntimeError(f'simulator exited with code {sim.proc.returncode}')
        spin(1.0)                       # the last fixes in flight
        if not fixes:
            raise RuntimeError('no fix received')

        stamps = [t for t, _, _ in fixes]
        x_true = np.array([true_position(t) for t in stamps])
        stats = track_crlb_statistics(
            [x for _, x, _ in fixes], [P for _, _, P in fixes], x_true,
            [s.trajectory.position(0.0) for s in sc.stations],
            [s.sigma_az for s in sc.stations],
            [s.sigma_el if s.dims == 2 else math.nan for s in sc.stations])
        n_epochs = len({b.stamp_ns for b in bearings})
        print(f'summary: {len(fixes)} fixes from {len(bearings)} bearings ({n_epochs} epochs); '
              f'RMSE {stats["rmse"]:.1f} m vs CRLB {stats["crlb_rms"]:.1f} m along the true '
              f'track: ratio {stats["ratio"]:.2f} (1.0 = efficient; with {len(fixes)} fixes '
              f'the ratio itself scatters by about ±{math.sqrt(0.5 / len(fixes)):.0%}); RMS '
              f'predicted 1σ {stats["mean_predicted"]:.1f} m', flush=True)
        t_grid = np.arange(0.0, args.duration, 0.5)
        track = np.asarray(sc.targets[0].trajectory.position(t_grid))
        rays = []
        for b in bearings:
            x = true_position(b.stamp_ns)
            rays.append((b.station, (np.asarray(b.position), b.azimuth,
                                     1.2 * np.linalg.norm((x - b.position)[:2]))))
        png = os.path.abspath(os.path.join(args.out, 'demo_fusion.png'))
        t_fix = np.array([(t - sc.epoch_ns) / NS_PER_S for t in stamps])
        write_png(png, sc, fixes, track, rays, stats, x_true, t_fix)
        print(f'png: {png}', flush=True)
        code = 0
    except RuntimeError as exc:
        print(f'demo: error: {exc}', file=sys.stderr, flush=True)
        for c in children:
            print(f'--- {c.name} ({c.log_path}) ---\n{c.tail()}', file=sys.stderr)
    finally:
        for c in reversed(children):
            rc = c.stop()
            if code == 0 and rc not in (0, -signal.SIGINT):
                print(f'demo: {c.name} exited with code {rc}', file=sys.stderr)
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return code


def _sigterm(signum, frame):
    raise KeyboardInterrupt


def main(argv=None):
    """Entry point: ``python -m bearing_loc_ros.demo``."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    # Ctrl-C and SIGTERM end the run through the cleanup path, even when this process was
    # started with SIGINT ignored (a background job of a non-interactive shell); children
    # exec'd afterwards then get the default SIGINT disposition too.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _sigterm)
    t0 = time.monotonic()
    try:
        code = run(args)
    except KeyboardInterrupt:
        print('demo: interrupted; children stopped', file=sys.stderr)
        return 130
    print(f'demo: {"done" if code == 0 else "FAILED"} in {time.monotonic() - t0:.1f} s wall',
          flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main())
