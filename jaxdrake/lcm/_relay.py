"""A loopback hub for LCM's `tcpq://` provider, so processes on one machine exchange messages
without a multicast group (tests, the example, a laptop with no network).

The protocol (LCM's `lcm_tcpq.c`): each side sends a 4-byte magic number and the protocol
version on connect; then the client sends frames `SUBSCRIBE(channel regex)`,
`UNSUBSCRIBE(channel regex)` and `PUBLISH(channel, data)`, and the hub forwards every PUBLISH
to each client with a matching subscription. All integers are big-endian uint32. The hub binds
127.0.0.1 only.
"""

from __future__ import annotations

import re
import socket
import struct
import threading

MAGIC_SERVER, MAGIC_CLIENT, VERSION = 0x287617FA, 0x287617FB, 0x0100
PUBLISH, SUBSCRIBE, UNSUBSCRIBE = 1, 2, 3


def _read_exactly(sock, size):
    data = bytearray()
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        if not chunk:
            raise ConnectionError("peer closed")
        data.extend(chunk)
    return bytes(data)


def _read_uint32(sock):
    return struct.unpack(">I", _read_exactly(sock, 4))[0]


class LoopbackRelay:
    """A `tcpq` hub on 127.0.0.1 (`port=0` picks a free port); `url` is what clients pass to
    `lcm.LCM`. Use as a context manager, or `start()` / `close()`."""

    def __init__(self, port: int = 0):
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", port))
        self._server.listen()
        self.port = self._server.getsockname()[1]
        self._clients: dict[socket.socket, list[re.Pattern]] = {}
        self._lock = threading.Lock()
        self._closed = False

    @property
    def url(self) -> str:
        return f"tcpq://127.0.0.1:{self.port}"

    def start(self) -> "LoopbackRelay":
        threading.Thread(target=self._accept, daemon=True).start()
        return self

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self._closed = True
        try:
            self._server.close()
        except OSError:
            pass
        with self._lock:
            for client in list(self._clients):
                try:
                    client.shutdown(socket.SHUT_RDWR)
                    client.close()
                except OSError:
                    pass
            self._clients.clear()

    def _accept(self):
        while not self._closed:
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client):
        try:
            client.sendall(struct.pack(">II", MAGIC_SERVER, VERSION))
            if _read_uint32(client) != MAGIC_CLIENT:
                raise ConnectionError("not an LCM tcpq client")
            _read_uint32(client)  # the client's protocol version
            with self._lock:
                self._clients[client] = []
            while True:
                kind = _read_uint32(client)
                channel = _read_exactly(client, _read_uint32(client)).decode("utf-8", "replace")
                if kind == PUBLISH:
                    data = _read_exactly(client, _read_uint32(client))
                    self._forward(channel, data)
                elif kind == SUBSCRIBE:
                    with self._lock:
                        self._clients[client].append(re.compile(channel))
                elif kind == UNSUBSCRIBE:
                    with self._lock:
                        self._clients[client] = [p for p in self._clients[client] if p.pattern != channel]
                else:
                    raise ConnectionError(f"unknown tcpq frame type {kind}")
        except (ConnectionError, OSError):
            pass
        finally:
            with self._lock:
                self._clients.pop(client, None)
            try:
                client.close()
            except OSError:
                pass

    def _forward(self, channel, data):
        encoded = channel.encode("utf-8")
        frame = struct.pack(">II", PUBLISH, len(encoded)) + encoded + struct.pack(">I", len(data)) + data
        with self._lock:
            targets = [c for c, patterns in self._clients.items() if any(p.fullmatch(channel) for p in patterns)]
        for client in targets:
            try:
                client.sendall(frame)
            except OSError:
                pass
