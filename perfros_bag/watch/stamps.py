"""A chain's latency, live: the receipt time minus ``header.stamp`` of its last topic's messages.

The watcher subscribes to a chain's last topic only while its messages are small
(:data:`STAMP_MAX_BYTES`: detections, not images): every message subscribed to is copied to
the watcher, across the link between its publisher's computer and the watcher's, and a
watcher subscribed to an image topic loads that link as one more consumer of the images
(RQ4 2026-11-28 04:30: two watchers of one deploy, each on ``/robotN/smooth/image``, 230 kB
at 5 Hz, offered 2 x 1,150 kB/s to 3,000 kB/s links that carried the plan's 1,170: the
people detector fed across such a link ran at 3.9-4.4 Hz of 5 after the re-plan, 12-20 %
below the plan). It subscribes the way any ROS 1 subscriber does, without a ROS client library: it asks
each publisher's XML-RPC ``requestTopic`` for a TCPROS endpoint, sends a connection header
(``md5sum: *``, the wildcard publishers accept from generic subscribers such as
``rostopic``) and reads the length-prefixed messages, decoding only the Header every
stamped message starts with (``uint32 seq``, ``uint32 secs``, ``uint32 nsecs``). It does not
register with the master. Its threads and sockets end with :meth:`StampListener.close`.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from urllib.parse import urlsplit

from perfros_bag.rosrun.master import CALLER_ID, TopicCounters, node_call

#: a chain's last topic whose messages average more bytes than this is not subscribed to
STAMP_MAX_BYTES = 16_384


def mean_message_bytes(topics: dict[tuple[str, str], TopicCounters], topic: str) -> float | None:
    """The mean payload bytes of ``topic``'s messages over every publisher's counters so far
    (a reading's ``topics``); None before any message was counted."""
    messages = payload = 0
    for (t, _publisher), c in topics.items():
        if t != topic:
            continue
        messages += sum(m for m, _ in c.connections.values())
        payload += c.total_bytes if c.total_bytes is not None else sum(b for _, b in c.connections.values())
    return payload / messages if messages else None


def connection_header(fields: dict[str, str]) -> bytes:
    """A TCPROS connection header: each ``key=value`` length-prefixed, the whole too."""
    body = b"".join(struct.pack("<I", len(f)) + f for f in (f"{k}={v}".encode() for k, v in fields.items()))
    return struct.pack("<I", len(body)) + body


def header_stamp(message: bytes) -> float | None:
    """The ``header.stamp`` (seconds) of a serialised message that starts with a Header."""
    if len(message) < 12:
        return None
    _seq, secs, nsecs = struct.unpack_from("<III", message)
    return secs + nsecs / 1e9


def _read_exact(sock: socket.socket, n: int, closed: threading.Event | None = None) -> bytes | None:
    """``n`` bytes; None at the end of the stream or once ``closed`` is set (a socket timeout
    only gives ``closed`` a chance: the read goes on where it was)."""
    buf = bytearray()
    while len(buf) < n:
        try:
            chunk = sock.recv(n - len(buf))
        except TimeoutError:
            if closed is not None and not closed.is_set():
                continue
            raise
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


class StampListener:
    """Subscribes to ``topic`` at each of ``publishers`` (XML-RPC URIs); collects latencies."""

    def __init__(self, topic: str, msgtype: str, publishers: list[str], timeout: float = 3.0) -> None:
        self.topic = topic
        self.msgtype = msgtype
        self.timeout = timeout
        self.latencies: list[float] = []
        self.lock = threading.Lock()
        self.closed = threading.Event()
        self.sockets: list[socket.socket] = []
        self.threads: list[threading.Thread] = []
        self.listening: dict[str, threading.Thread] = {}  # publisher URI -> its thread
        self.follow(publishers)

    def follow(self, publishers: list[str]) -> None:
        """Listen to each of ``publishers`` not listened to now: a publisher restarted under
        its name (a new URI), or one whose connection ended, is connected to again."""
        for uri in publishers:
            if self.closed.is_set():
                return
            t = self.listening.get(uri)
            if t is not None and t.is_alive():
                continue
            t = threading.Thread(target=self._listen, args=(uri,), daemon=True)
            self.listening[uri] = t
            self.threads = [x for x in self.threads if x.is_alive()] + [t]
            t.start()

    def _connect(self, uri: str) -> socket.socket | None:
        reply = node_call(uri, "requestTopic", self.topic, [["TCPROS"]])
        if not isinstance(reply, list) or len(reply) < 3 or reply[0] != "TCPROS":
            return None
        host = str(reply[1]) or (urlsplit(uri).hostname or "localhost")
        sock = socket.create_connection((host, int(reply[2])), timeout=self.timeout)
        sock.sendall(connection_header({"callerid": CALLER_ID + "_watch", "topic": self.topic, "md5sum": "*",
                                        "type": self.msgtype or "*", "tcp_nodelay": "1"}))
        size = _read_exact(sock, 4)
        if size is None or _read_exact(sock, struct.unpack("<I", size)[0]) is None:
            sock.close()
            return None
        sock.settimeout(0.5)
        return sock

    def _listen(self, uri: str) -> None:
        try:
            sock = self._connect(uri)
        except OSError:
            return
        if sock is None:
            return
        with self.lock:
            if self.closed.is_set():
                sock.close()
                return
            self.sockets.append(sock)
        try:
            while not self.closed.is_set():
                size = _read_exact(sock, 4, self.closed)
                message = None if size is None else _read_exact(sock, struct.unpack("<I", size)[0], self.closed)
                if message is None:
                    break
                stamp = header_stamp(message)
                if stamp is not None and stamp > 0:
                    with self.lock:
                        self.latencies.append(time.time() - stamp)
        except OSError:
            pass
        finally:  # the publisher went away (or we close): follow() may connect again
            with self.lock:
                if sock in self.sockets:
                    self.sockets.remove(sock)
            try:
                sock.close()
            except OSError:
                pass

    def take(self) -> list[float]:
        """The latencies (seconds) collected since the last call."""
        with self.lock:
            out, self.latencies = self.latencies, []
        return out

    def close(self) -> None:
        self.closed.set()
        with self.lock:
            for s in self.sockets:
                try:
                    s.close()
                except OSError:
                    pass
        for t in self.threads:
            t.join(timeout=self.timeout + 1.0)


def percentile(xs: list[float], q: float) -> float:
    """The ``q``-th percentile (0-100) by linear interpolation between order statistics
    (numpy's default), without numpy."""
    s = sorted(xs)
    pos = (len(s) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)
