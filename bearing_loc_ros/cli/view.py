"""``bearing_loc view``: a Foxglove WebSocket server of the live topics, or of bags.

Live (default): runs the ``view_node`` node in this process (rclpy); every flag maps to a
node parameter. ``--bag PATH [PATH ...]``: serves recorded bags instead (no ROS graph
needed), merged by bag time, paced at ``--rate`` x real time; the server time follows the
bag's ``/clock``. Connect Foxglove or Lichtblick to ``ws://HOST:PORT``.
"""

import signal
import sys
import threading

from . import InputError


def add_arguments(parser):
    """Command line of ``bearing_loc view``."""
    parser.description = __doc__.splitlines()[0]
    parser.add_argument('--bag', nargs='+', default=None, metavar='PATH',
                        help='serve these bag directories instead of the live topics')
    parser.add_argument('--host', default='127.0.0.1',
                        help='address to listen on (default 127.0.0.1; anything else exposes '
                             'the server to the network)')
    parser.add_argument('--port', type=int, default=8765, help='TCP port (default 8765)')
    parser.add_argument('--origin', type=float, nargs=3, default=None,
                        metavar=('LAT_DEG', 'LON_DEG', 'ALT_M'),
                        help='geodetic origin of the ENU frame: enables /map_geojson and '
                             'station NavSatFix topics')
    parser.add_argument('--frame-id', default='map',
                        help='world (ENU) frame of the fixes and bearings drawn on the map '
                             "(default map; the fusion node's frame_id)")
    parser.add_argument('--rate', type=float, default=1.0, help='bag replay speed factor')
    parser.add_argument('--loop', action='store_true', help='replay the bags again when done')
    parser.add_argument('--topics', nargs='+', default=None,
                        help="forward only these topics (default: the package's topics)")
    parser.add_argument('--use-sim-time', action='store_true',
                        help='live: run with use_sim_time (server time from /clock)')
    parser.add_argument('--max-backlog', type=int, default=None,
                        help='messages queued per client before the oldest is dropped')


def _check(args):
    from ..core.conventions import check_frame_id
    try:
        check_frame_id(args.frame_id, '--frame-id')
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if not 0 <= args.port <= 65535:
        raise InputError(f'--port: must be 0..65535, got {args.port}')
    if not args.rate > 0 or args.rate != args.rate or args.rate == float('inf'):
        raise InputError(f'--rate: must be a finite number > 0, got {args.rate}')
    if args.max_backlog is not None and not 1 <= args.max_backlog <= 1_000_000:
        raise InputError(f'--max-backlog: must be 1..1000000, got {args.max_backlog}')
    if args.origin is not None:
        from ..core.gis import check_origin
        try:
            check_origin(args.origin)
        except ValueError as exc:
            raise InputError(str(exc)) from None


def run_bag(args):
    """Serve bags until they end (or Ctrl-C; forever with --loop)."""
    from .. import bagio
    from ..foxglove_view import bag_plan, DEFAULT_BACKLOG, FoxgloveView, serve_bag
    topics = set(args.topics) if args.topics else None
    for p in args.bag:
        try:
            bagio.BagReader(p)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    try:
        bag_plan(args.bag, topics)      # nothing to serve: an error before listening
    except ValueError as exc:
        raise InputError(str(exc)) from None
    try:
        view = FoxgloveView(host=args.host, port=args.port, origin=args.origin, use_time=True,
                            backlog=args.max_backlog or DEFAULT_BACKLOG,
                            frame_id=args.frame_id)
    except RuntimeError as exc:
        print(f'bearing_loc view: cannot listen on {args.host}:{args.port}: {exc}',
              file=sys.stderr)
        return 1
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print(f'serving {" + ".join(args.bag)} on ws://{args.host}:{view.port} '
          f'(foxglove.sdk.v1), rate {args.rate:g}', flush=True)
    try:
        n = serve_bag(view, args.bag, args.rate, args.loop, stop, topics,
                      log=lambda text: print(text, file=sys.stderr, flush=True))
        print(f'{n} messages forwarded; {view.stats()}', flush=True)
        if not stop.is_set():
            print('replay done; serving the last picture until Ctrl-C', flush=True)
            stop.wait()
    finally:
        view.stop()
    return 0


def run_live(args):
    """Run view_node in this process with parameters from the flags."""
    from ..view_node import main
    import json
    ros = ['--ros-args', '-p', f'host:={args.host}', '-p', f'port:={args.port}',
           '-p', f'frame_id:={json.dumps(args.frame_id)}']     # a YAML string, '123' too
    if args.origin is not None:
        ros += ['-p', 'geodetic_origin:=[' + ','.join(f'{v!r}' for v in args.origin) + ']']
    if args.topics:
        ros += ['-p', 'topics:=[' + ','.join(f'"{t}"' for t in args.topics) + ']']
    if args.use_sim_time:
        ros += ['-p', 'use_sim_time:=true']
    if args.max_backlog is not None:
        ros += ['-p', f'max_backlog:={args.max_backlog}']
    try:
        main(['bearing_loc_view'] + ros)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def run(args):
    """Entry point of the verb."""
    _check(args)
    return run_bag(args) if args.bag else run_live(args)
