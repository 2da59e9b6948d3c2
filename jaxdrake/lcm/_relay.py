"""A loopback hub for LCM's `tcpq://` provider, so processes on one machine exchange messages
without a multicast group (tests, the example, a laptop with no network).

The protocol (LCM's `lcm_tcpq.c`): each side sends a 4-byte magic number and the protocol
version on connect; then the client sends frames `SUBSCRIBE(pattern)`, `UNSUBSCRIBE(pattern)`
and `PUBLISH(channel, data)`, and the hub forwards every PUBLISH to each client with a
subscription whose pattern matches the whole channel name. All integers are big-endian uint32.

Every client is a peer the hub does not trust:

- patterns are `ChannelPattern`s (`_channels.py`), matched in linear time, outside the hub's
  lock, each (pattern, channel) pair once;
- each client has its own queue of at most `queue_bytes` and its own writer thread: a client
  that reads slowly loses its own oldest messages (counted in `dropped`, logged once per
  client), never delays the others;
- a request the hub refuses (a pattern outside the language, more than `MAX_SUBSCRIPTIONS`
  patterns, a channel name longer than `MAX_LENGTH`, a PUBLISH on `RELAY_ERROR_CHANNEL`) is
  answered with a PUBLISH frame on `RELAY_ERROR_CHANNEL` whose data is the reason in UTF-8,
  sent to that client only. Any tcpq client reads it as an ordinary message (LCM's C client
  drops it unless subscribed; jaxdrake's `open_lcm` subscribes and logs it); only the hub
  publishes there.

The hub binds 127.0.0.1 unless `host` names another address.
"""

from __future__ import annotations

import collections
import logging
import socket
import struct
import threading
import time

from ._channels import MAX_LENGTH, ChannelPattern, PatternError

log = logging.getLogger("jaxdrake.lcm")

MAGIC_SERVER, MAGIC_CLIENT, VERSION = 0x287617FA, 0x287617FB, 0x0100
PUBLISH, SUBSCRIBE, UNSUBSCRIBE = 1, 2, 3
RELAY_ERROR_CHANNEL = "JAXDRAKE_RELAY_ERROR"
MAX_SUBSCRIPTIONS = 1024  # per client: every PUBLISH is matched against all of them
HANDSHAKE_TIMEOUT = 5.0  # s; a client silent this long after connecting is dropped
_CHUNK = 1 << 20  # read at most this much at a time: a length prefix never allocates by itself


def _read_exactly(sock, size):
    data = bytearray()
    while len(data) < size:
        chunk = sock.recv(min(size - len(data), _CHUNK))
        if not chunk:
            raise ConnectionError("peer closed")
        data.extend(chunk)
    return bytes(data)


def _read_uint32(sock):
    return struct.unpack(">I", _read_exactly(sock, 4))[0]


def publish_frame(channel: str, data: bytes) -> bytes:
    encoded = channel.encode("utf-8")
    return struct.pack(">II", PUBLISH, len(encoded)) + encoded + struct.pack(">I", len(data)) + data


class _Client:
    """One connection: its subscriptions (a tuple only its reader thread replaces) and its
    own bounded queue, drained by its own writer thread."""

    def __init__(self, sock, queue_bytes):
        self.sock, self.queue_bytes = sock, queue_bytes
        self.name = "%s:%d" % sock.getpeername()[:2]
        self.patterns: tuple[ChannelPattern, ...] = ()
        self.dropped = 0
        self.closed = False
        self._queue, self._queued = collections.deque(), 0
        self._ready = threading.Condition()

    def wants(self, channel: str) -> bool:
        return any(pattern.fullmatch(channel) for pattern in self.patterns)

    def offer(self, frame: bytes):
        """Queue `frame`; past `queue_bytes`, drop the oldest queued frames (never the newest)."""
        with self._ready:
            if self.closed:
                return
            self._queue.append(frame)
            self._queued += len(frame)
            while self._queued > self.queue_bytes and len(self._queue) > 1:
                self._queued -= len(self._queue.popleft())
                if self.dropped == 0:
                    log.warning("relay: client %s reads too slowly; dropping its oldest messages", self.name)
                self.dropped += 1
            self._ready.notify()

    def refuse(self, reason: str):
        log.info("relay: refused a request of client %s: %s", self.name, reason)
        self.offer(publish_frame(RELAY_ERROR_CHANNEL, reason.encode("utf-8")))

    def write(self):
        """The writer thread: send queued frames until the connection closes."""
        try:
            while True:
                with self._ready:
                    while not self._queue and not self.closed:
                        self._ready.wait()
                    if self.closed:
                        return
                    frame = self._queue.popleft()
                    self._queued -= len(frame)
                self.sock.sendall(frame)
        except OSError:
            pass
        finally:
            self.stop()

    def stop(self):
        """Close the queue and shut the socket down: wakes the reader and a blocked writer."""
        with self._ready:
            self.closed = True
            self._queue.clear()
            self._ready.notify()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


class LoopbackRelay:
    """A `tcpq` hub on `host` (127.0.0.1 by default; `port=0` picks a free port); `url` is what
    clients pass to `lcm.LCM`. Each client's queue holds at most `queue_bytes` of messages;
    `dropped` counts the messages dropped from slow clients' queues. Use as a context manager,
    or `start()` / `close()`."""

    def __init__(self, port: int = 0, *, host: str = "127.0.0.1", queue_bytes: int = 16 << 20):
        if not queue_bytes > 0:
            raise ValueError(f"queue_bytes must be positive, got {queue_bytes}")
        self.queue_bytes = int(queue_bytes)
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind((host, port))
        self._server.listen()
        self.address: tuple[str, int] = self._server.getsockname()
        self._clients: set[_Client] = set()
        self._lock = threading.Lock()  # guards _clients, _dropped_by_gone and _threads only
        self._dropped_by_gone = 0
        self._threads: list[threading.Thread] = []
        self._closed = False

    @property
    def port(self) -> int:
        return self.address[1]

    @property
    def url(self) -> str:
        return f"tcpq://{self.address[0]}:{self.port}"

    @property
    def dropped(self) -> int:
        """Messages dropped from slow clients' queues since the start."""
        with self._lock:
            return self._dropped_by_gone + sum(client.dropped for client in self._clients)

    def start(self) -> "LoopbackRelay":
        self._spawn(self._accept, "accept")
        return self

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    def close(self, timeout: float = 2.0):
        """Stop accepting, disconnect every client, and wait for the hub's threads."""
        self._closed = True
        try:
            self._server.shutdown(socket.SHUT_RDWR)  # wakes accept(), which close() alone does not
        except OSError:
            pass
        self._server.close()
        with self._lock:
            clients = list(self._clients)
        for client in clients:
            client.stop()
        # until none is left: a connection accepted just before the shutdown starts its thread
        # after a first look at the threads (it sees the hub closed and ends at once)
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                pending = [t for t in self._threads if t.is_alive() and t is not threading.current_thread()]
            if not pending or time.monotonic() >= deadline:
                return
            for thread in pending:
                thread.join(max(deadline - time.monotonic(), 0.0))

    def _spawn(self, target, role, *args):
        thread = threading.Thread(target=target, args=args, daemon=True, name=f"LoopbackRelay-{self.port}-{role}")
        with self._lock:  # started under the lock: an unstarted thread is not alive, and pruning would drop it
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]
            thread.start()
        return thread

    def _accept(self):
        while not self._closed:
            try:
                sock, _ = self._server.accept()
            except OSError:
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._spawn(self._serve, "client", sock)

    def _serve(self, sock):
        """A client's reader thread: handshake, then its frames until it disconnects."""
        try:
            client = _Client(sock, self.queue_bytes)
        except OSError:  # gone before it was seen
            sock.close()
            return
        with self._lock:
            if self._closed:
                sock.close()
                return
            self._clients.add(client)  # from here close() can stop it, in the handshake too
        writer = None
        try:
            sock.settimeout(HANDSHAKE_TIMEOUT)
            sock.sendall(struct.pack(">II", MAGIC_SERVER, VERSION))
            if _read_uint32(sock) != MAGIC_CLIENT:
                raise ConnectionError("not an LCM tcpq client")
            _read_uint32(sock)  # the client's protocol version
            sock.settimeout(None)
            writer = self._spawn(client.write, "writer")
            while not client.closed:
                self._handle_frame(client)
        except OSError as error:  # ConnectionError and timeouts too
            if not client.closed:
                log.debug("relay: client %s disconnected: %s", client.name, error)
        finally:
            client.stop()
            if writer is not None:
                writer.join()
            sock.close()
            with self._lock:
                self._clients.discard(client)
                self._dropped_by_gone += client.dropped

    def _handle_frame(self, client):
        kind = _read_uint32(client.sock)
        if kind not in (PUBLISH, SUBSCRIBE, UNSUBSCRIBE):
            raise ConnectionError(f"unknown tcpq frame type {kind}")  # the stream cannot be parsed on
        channel = _read_exactly(client.sock, _read_uint32(client.sock)).decode("utf-8", "replace")
        if kind == PUBLISH:
            data = _read_exactly(client.sock, _read_uint32(client.sock))
            if channel == RELAY_ERROR_CHANNEL:
                client.refuse(f"only the relay publishes on {RELAY_ERROR_CHANNEL}")
            elif len(channel) > MAX_LENGTH:
                client.refuse(f"channel name longer than {MAX_LENGTH} characters: {channel[:40]!r}...")
            else:
                self._forward(channel, data)
        elif kind == SUBSCRIBE and len(client.patterns) >= MAX_SUBSCRIPTIONS:
            client.refuse(f"subscription {channel[:MAX_LENGTH]!r} refused: more than {MAX_SUBSCRIPTIONS} subscriptions")
        elif kind == SUBSCRIBE:
            try:
                client.patterns += (ChannelPattern(channel),)
            except PatternError as error:
                client.refuse(f"subscription {channel[:MAX_LENGTH]!r} refused: {error}")
        else:  # one UNSUBSCRIBE ends one SUBSCRIBE of that pattern (LCM's client sends one each)
            texts = [pattern.text for pattern in client.patterns]
            if channel in texts:
                k = texts.index(channel)
                client.patterns = client.patterns[:k] + client.patterns[k + 1:]

    def _forward(self, channel, data):
        frame = publish_frame(channel, data)
        with self._lock:
            clients = tuple(self._clients)
        for client in clients:  # matching outside the lock: a slow pattern delays only this sender
            if client.wants(channel):
                client.offer(frame)
