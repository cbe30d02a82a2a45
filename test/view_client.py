"""A minimal client of the Foxglove WebSocket protocol (subprotocol foxglove.sdk.v1).

Written from the protocol specification (foxglove/ws-protocol docs/spec.md), on the
``websockets`` package, independent of foxglove-sdk:

* text frames are JSON objects with an ``op``: ``serverInfo``, ``advertise`` (channels with
  id, topic, encoding, schemaName, schema, schemaEncoding), ``unadvertise``, ``status``...;
* binary frames start with a 1-byte opcode: 0x01 Message Data = uint32 subscription id,
  uint64 log time (ns), payload; 0x02 Time = uint64 server time (ns); little endian;
* the client subscribes with ``{"op": "subscribe", "subscriptions": [{"id", "channelId"}]}``.
"""

import asyncio
import json
import struct

import websockets

SUBPROTOCOL = 'foxglove.sdk.v1'
OP_MESSAGE_DATA = 0x01
OP_TIME = 0x02


class FoxgloveClient:
    """One connection; collects channels, messages per topic and server times."""

    def __init__(self, url):
        self.url = url
        self.ws = None
        self.server_info = None
        self.channels = {}        # channel id -> advertise dict
        self.by_topic = {}        # topic -> channel dict
        self.subs = {}            # subscription id -> topic
        self.messages = {}        # topic -> [(log_time_ns, payload bytes)]
        self.times = []
        self._next_sub = 1

    async def connect(self, max_size=2 ** 24):
        """Open the WebSocket with the Foxglove subprotocol."""
        self.ws = await websockets.connect(self.url, subprotocols=[SUBPROTOCOL],
                                           max_size=max_size, open_timeout=10)
        if self.ws.subprotocol != SUBPROTOCOL:
            raise RuntimeError(f'server chose subprotocol {self.ws.subprotocol!r}')
        return self

    def _handle(self, frame):
        if isinstance(frame, str):
            msg = json.loads(frame)
            op = msg.get('op')
            if op == 'serverInfo':
                self.server_info = msg
            elif op == 'advertise':
                for ch in msg['channels']:
                    self.channels[ch['id']] = ch
                    self.by_topic[ch['topic']] = ch
            elif op == 'unadvertise':
                for cid in msg['channelIds']:
                    ch = self.channels.pop(cid, None)
                    if ch:
                        self.by_topic.pop(ch['topic'], None)
            return
        op = frame[0]
        if op == OP_MESSAGE_DATA:
            sub, t = struct.unpack_from('<IQ', frame, 1)
            topic = self.subs.get(sub)
            if topic is not None:
                self.messages.setdefault(topic, []).append((t, bytes(frame[13:])))
        elif op == OP_TIME:
            self.times.append(struct.unpack_from('<Q', frame, 1)[0])

    async def pump(self, duration, until=None):
        """Receive for up to ``duration`` s, or until ``until(self)`` is true."""
        loop = asyncio.get_running_loop()
        end = loop.time() + duration
        while loop.time() < end:
            if until is not None and until(self):
                return True
            try:
                frame = await asyncio.wait_for(self.ws.recv(),
                                               max(0.01, min(0.2, end - loop.time())))
            except asyncio.TimeoutError:
                continue
            self._handle(frame)
        return until(self) if until is not None else True

    async def subscribe(self, topics, again=False):
        """Subscribe to the advertised channels of ``topics``; return the topics subscribed.

        ``again``: subscribe anew to topics already subscribed (a server that has just
        advertised a channel can answer a subscription to it with "unknown channel" and
        drop it: foxglove-sdk advertises before its own lookup table has the channel)."""
        subs, done = [], []
        for topic in topics:
            ch = self.by_topic.get(topic)
            if ch is not None and again:
                self.subs = {k: v for k, v in self.subs.items() if v != topic}
            if ch is None or topic in self.subs.values():
                continue
            sid = self._next_sub
            self._next_sub += 1
            self.subs[sid] = topic
            subs.append({'id': sid, 'channelId': ch['id']})
            done.append(topic)
        if subs:
            await self.ws.send(json.dumps({'op': 'subscribe', 'subscriptions': subs}))
        return done

    async def close(self):
        """Close the connection politely."""
        if self.ws is not None:
            await self.ws.close()


def geojson_payload(payload):
    """The ``geojson`` string of a foxglove.GeoJSON protobuf payload (field 1, type string).

    Protobuf wire format: tag 0x0a (field 1, length-delimited), varint length, UTF-8 bytes.
    """
    if not payload:
        return ''
    if payload[0] != 0x0a:
        raise ValueError(f'unexpected protobuf tag {payload[0]:#x}')
    n, shift, i = 0, 0, 1
    while True:
        b = payload[i]
        n |= (b & 0x7f) << shift
        i += 1
        if not b & 0x80:
            break
        shift += 7
    return payload[i:i + n].decode('utf-8')
