"""How many datagrams the kernel dropped for a UDP socket (no ROS).

A station that reads its UDP socket less often than datagrams arrive loses the excess in the
kernel: once the socket's receive queue (SO_RCVBUF bytes) is full, each further datagram is
discarded and the socket's drop counter ``sk_drops`` is incremented. Those datagrams never
reach the node, so they cannot be counted by reason like the ones it rejects; this counter
is the only trace of them. :func:`udp_drops` reads it:

1. ``getsockopt(SOL_SOCKET, SO_MEMINFO)`` (Linux ≥ 4.6): an array of u32 whose element
   ``SK_MEMINFO_DROPS`` (8) is ``sk_drops``; one system call, independent of how many
   sockets the host has.
2. Otherwise the ``drops`` column (13th) of ``/proc/self/net/udp`` or ``udp6``, on the line
   whose ``inode`` column (10th) is the socket's inode (``os.fstat(fd).st_ino``).
   ``/proc/self/net`` is the calling process's network namespace.
3. ``None`` where neither exists (not Linux, socket closed).

The counter is the kernel's 32-bit one (it wraps after 2³² drops) and counts since the
socket was created.
"""

import os
import socket
import struct
import sys

#: Linux SO_MEMINFO option number (include/uapi/asm-generic/socket.h) and the index of
#: SK_MEMINFO_DROPS in its u32 array (include/uapi/linux/sock_diag.h).
SO_MEMINFO = 55
SK_MEMINFO_DROPS = 8
_MEMINFO_BYTES = 4 * (SK_MEMINFO_DROPS + 1)
_PROC_TABLES = ('/proc/self/net/udp', '/proc/self/net/udp6')
_INODE_COLUMN, _DROPS_COLUMN = 9, 12


def _drops_meminfo(sock):
    """sk_drops from SO_MEMINFO, or None when the kernel does not report it."""
    if not sys.platform.startswith('linux'):
        return None
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, _MEMINFO_BYTES)
    except (OSError, ValueError):
        return None
    if len(raw) < _MEMINFO_BYTES:
        return None
    return struct.unpack_from('=I', raw, 4 * SK_MEMINFO_DROPS)[0]


def _drops_proc(sock, tables=_PROC_TABLES):
    """The ``drops`` column of the socket's line in /proc/self/net/udp{,6}, or None."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
    except (OSError, ValueError):
        return None
    for path in tables:
        try:
            with open(path, encoding='ascii') as f:
                next(f, None)  # header line
                for line in f:
                    cols = line.split()
                    if len(cols) > _DROPS_COLUMN and cols[_INODE_COLUMN] == inode:
                        return int(cols[_DROPS_COLUMN])
        except (OSError, ValueError):
            continue
    return None


def udp_drops(sock):
    """Datagrams the kernel dropped for UDP socket ``sock`` since it was opened, or None.

    Drops happen when the receive queue is full (the reader is busy or slower than the
    sender); the count comes from ``SO_MEMINFO`` or ``/proc/self/net/udp{,6}`` (module
    docstring) and is None where the platform reports neither. Never raises.
    """
    n = _drops_meminfo(sock)
    return n if n is not None else _drops_proc(sock)
