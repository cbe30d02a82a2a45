"""Memory of the Foxglove view server with a stalled client (bounded by the per-client backlog).

A child process runs :class:`bearing_loc_ros.foxglove_view.FoxgloveView` on loopback and
forwards serialized nav_msgs/OccupancyGrid messages (200 x 200 cells, ~40 kB, the size of
a large accuracy map) at RATE Hz for DURATION s. One client subscribes and then stops
reading (its transport is paused, so the TCP buffers and then the server's queue fill up);
a second, healthy client reads everything. The child's resident set size (VmRSS) is sampled
every second. Prints the figures; exits 1 if the RSS growth after the first phase exceeds
the expected bound (backlog x message size + 64 MiB slack).

Usage: python bench/bench_view_memory.py [--rate 200] [--duration 20] [--backlog 512]
"""
import argparse
import asyncio
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), 'test'))

SERVER = r'''
import sys, time
from nav_msgs.msg import OccupancyGrid
from rclpy.serialization import serialize_message
from bearing_loc_ros.foxglove_view import FoxgloveView
rate, duration, backlog = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
g = OccupancyGrid()
g.header.frame_id = 'map'
g.info.width = g.info.height = 200
g.data = [k % 100 for k in range(200 * 200)]
raw = serialize_message(g)
view = FoxgloveView(port=0, backlog=backlog)
view.advertise('/accuracy_map', 'nav_msgs/msg/OccupancyGrid')
print(view.port, len(raw), flush=True)
sys.stdin.readline()                      # wait until the clients are subscribed
t0 = time.monotonic()
n = 0
while time.monotonic() - t0 < duration:
    view.forward('/accuracy_map', 'nav_msgs/msg/OccupancyGrid', raw, time.time_ns())
    n += 1
    time.sleep(max(0.0, t0 + n / rate - time.monotonic()))
print('forwarded', n, view.forwarded_bytes, flush=True)
sys.stdin.readline()
view.stop()
'''


def rss_mib(pid):
    with open(f'/proc/{pid}/status', encoding='ascii') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    return float('nan')


async def main(args):
    from view_client import FoxgloveClient
    child = subprocess.Popen([sys.executable, '-c', SERVER, str(args.rate), str(args.duration),
                              str(args.backlog)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)
    try:
        port, size = map(int, child.stdout.readline().split())
        url = f'ws://127.0.0.1:{port}'
        base = rss_mib(child.pid)
        stalled = await FoxgloveClient(url).connect()
        healthy = await FoxgloveClient(url).connect()
        for c in (stalled, healthy):
            await c.pump(5.0, lambda c: '/accuracy_map' in c.by_topic)
            await c.subscribe(['/accuracy_map'])
        await stalled.pump(0.5)
        stalled.ws.transport.pause_reading()
        child.stdin.write('go\n')
        child.stdin.flush()
        samples = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.duration + 1.0:
            await healthy.pump(1.0)
            samples.append((time.monotonic() - t0, rss_mib(child.pid)))
        line = await asyncio.get_running_loop().run_in_executor(None, child.stdout.readline)
        _, n, nbytes = line.split()
        got = len(healthy.messages.get('/accuracy_map', ()))
        stalled.ws.transport.abort()
        await healthy.close()
        child.stdin.write('stop\n')
        child.stdin.flush()
        child.wait(20)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    half = [r for t, r in samples if t >= args.duration / 2]
    peak = max(r for _, r in samples)
    bound = args.backlog * size / 2 ** 20 + 64.0
    print(f'message {size} B at {args.rate:g} Hz for {args.duration:g} s: {n} forwarded '
          f'({int(nbytes) / 2 ** 20:.0f} MiB), healthy client received {got}')
    print(f'server RSS: {base:.1f} MiB before clients, peak {peak:.1f} MiB, '
          f'second half {min(half):.1f}..{max(half):.1f} MiB '
          f'(backlog {args.backlog} x {size} B = {args.backlog * size / 2 ** 20:.1f} MiB)')
    print('samples (s, MiB): ' + ', '.join(f'{t:.0f}:{r:.0f}' for t, r in samples))
    return 0 if peak - base <= bound else 1


if __name__ == '__main__':
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--rate', type=float, default=200.0)
    p.add_argument('--duration', type=float, default=20.0)
    p.add_argument('--backlog', type=int, default=512)
    sys.exit(asyncio.run(main(p.parse_args())))
