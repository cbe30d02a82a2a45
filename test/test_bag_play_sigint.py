"""`bearing_loc bag play` stops cleanly on SIGINT, as its docstring promises.

A shell starts background jobs (`bearing_loc bag play run1 &`) with SIGINT ignored. rclpy's
signal handler then shut the context down without a KeyboardInterrupt, and the player's next
publish raised RCLError: a traceback and exit code 1 instead of a clean stop.
"""
import os
import signal
import sys
import time

from bearing_loc_ros.cli.bag import simulate_bag
from bearing_loc_ros.core.simulation import load_scenario

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STATIC3 = os.path.join(REPO, 'config', 'scenarios', 'static3.yaml')


def test_bag_play_stops_cleanly_on_sigint(tmp_path):
    from ros_helpers import node_env, NodeProcess
    bag = tmp_path / 'run'
    # 60 s of bag time at rate 1: still playing when the signal arrives.
    simulate_bag(load_scenario(STATIC3), bag, duration=60.0, seed=0)
    # SIGINT ignored at start, as in a background job of a non-interactive shell.
    code = ('import signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); '
            'from bearing_loc_ros.cli import main; sys.exit(main(sys.argv[1:]))')
    # --wait-for-subscribers: the 'no subscriber yet' line tells that playback has started
    # (inside the player's try block), so the signal does not hit the interpreter start-up.
    with NodeProcess([sys.executable, '-c', code, 'bag', 'play', str(bag),
                      '--wait-for-subscribers', '0.3'], env=node_env()) as p:
        deadline = time.monotonic() + 30.0
        while 'bag play:' not in p.output() and p.running() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert p.running(), p.tail()
        assert 'bag play:' in p.output(), p.tail()
        time.sleep(0.5)
        p.proc.send_signal(signal.SIGINT)
        rc = p.wait(10.0)
        out = p.output()
    assert rc == 0, out
    assert 'Traceback' not in out, out
