"""`--ros-tcp HOST:PORT`: a client of Unity's ROS-TCP-Endpoint (v0.7.0), as OPERA's Unity simulators connect to it.

The protocol, as the endpoint's server code reads it (ros_tcp_endpoint/client.py, server.py, tcp_sender.py):
- every frame, both ways: uint32 LE length + UTF-8 destination, uint32 LE length + payload;
- the endpoint speaks first: `__handshake` with JSON {"version": "v0.7.0", "metadata": "{\"protocol\": \"ROS1\"}"}
  (or ROS2); the protocol chooses the payload format: ROS 1 serialisation or CDR (ROS 2, with its 4-byte
  encapsulation header, as rclpy's serialize_message gives);
- system commands are destinations starting with `__` and a JSON payload: `__subscribe` {topic, message_name}
  asks the endpoint to forward a ROS topic to us, `__publish` {topic, message_name, queue_size, latch} lets us
  publish on one; message_name is "pkg/Type". The ROS 2 endpoint drops the last byte of a command's JSON (Unity's
  CDR strings end in NUL), so one is appended for ROS 2 only (the ROS 1 endpoint would reject it);
- a destination that is a topic carries one serialised message; the endpoint answers mistakes with `__error` /
  `__warn` / `__log` JSON {"text"}; an empty destination is a keep-alive.
The endpoint has no `__remove_*` handlers (sending one drops the connection) and forwards subscribed topics only to
its most recent connection. A lost connection is retried every second and the topics registered again.
"""
from __future__ import annotations

import json
import socket
import struct
import threading

from ..errors import UserError

HANDSHAKE_TIMEOUT = 10.0
RECONNECT_INTERVAL = 1.0
MAX_DESTINATION = 1024          # bytes of a topic or system destination name
MAX_PAYLOAD = 64 * 1024 * 1024  # bytes of one message the endpoint sends us (commands, its log lines)


def parse_address(text: str, what: str = "--ros-tcp") -> tuple[str, int]:
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UserError(f"{what}: expected HOST:PORT (e.g. 127.0.0.1:10000), got {text!r}")
    return host.strip("[]"), int(port)


def frame(destination: str, payload: bytes) -> bytes:
    dest = destination.encode("utf-8")
    return struct.pack("<I", len(dest)) + dest + struct.pack("<I", len(payload)) + payload


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray(n)
    view, pos = memoryview(buf), 0
    while pos < n:
        got = sock.recv_into(view[pos:], n - pos)
        if not got:
            raise ConnectionError("the endpoint closed the connection")
        pos += got
    return bytes(buf)


def read_frame(sock: socket.socket) -> tuple[str, bytes]:
    """One frame; ConnectionError for bytes that are no frame (the stream is lost: the caller reconnects), before
    a length from the peer allocates anything beyond the limits."""
    (n,) = struct.unpack("<I", _recv_exact(sock, 4))
    if n > MAX_DESTINATION:
        raise ConnectionError(f"not a ROS-TCP frame (a destination of {n} bytes)")
    try:
        destination = _recv_exact(sock, n).decode("utf-8").rstrip("\x00")
    except UnicodeDecodeError:
        raise ConnectionError("not a ROS-TCP frame (a destination that is not UTF-8)") from None
    (m,) = struct.unpack("<I", _recv_exact(sock, 4))
    if m > MAX_PAYLOAD:
        raise ConnectionError(f"not a ROS-TCP frame (a message of {m} bytes to {destination[:80]!r})")
    return destination, _recv_exact(sock, m)


def _greeting(payload: bytes) -> tuple[str | None, str]:
    """(version, protocol) of the endpoint's __handshake JSON; ValueError for anything else."""
    hello = json.loads(payload.decode("utf-8").rstrip("\x00"))
    if not isinstance(hello, dict):
        raise ValueError("a handshake that is no JSON object")
    metadata = hello.get("metadata") or "{}"
    if not isinstance(metadata, str):
        raise ValueError("a handshake whose metadata is no JSON text")
    meta = json.loads(metadata)
    protocol = meta.get("protocol", "ROS1") if isinstance(meta, dict) else None
    if protocol not in ("ROS1", "ROS2"):
        raise ValueError(f"unknown protocol {protocol!r}")
    version = hello.get("version")
    return (str(version) if version is not None else None), protocol


class RosTcpTransport:
    def __init__(self, address: str, log, *, connect_timeout: float = 10.0):
        self.host, self.port = parse_address(address)
        self._log = log
        self._send_lock = threading.Lock()
        self._sock_lock = threading.Lock()
        self._closing = threading.Event()
        self._subs: dict[str, tuple[str, object]] = {}
        self._pubs: dict[str, str] = {}
        self.sock = None
        self.version = None
        self.protocol = None
        self.dropped = 0
        self._connect(connect_timeout, first=True)
        self.ros_version = 1 if self.protocol == "ROS1" else 2
        self._reader = threading.Thread(target=self._read_loop, name="ros-tcp-reader", daemon=True)
        self._reader.start()

    # ------------------------------------------------------------------------------------------ connection
    def _connect(self, timeout: float, first: bool = False) -> None:
        where = f"{self.host}:{self.port}"
        try:
            sock = socket.create_connection((self.host, self.port), timeout=timeout)
        except OSError as exc:
            if first:
                raise UserError(f"--ros-tcp: cannot connect to a ROS-TCP-Endpoint at {where} ({exc.strerror or exc}); "
                                f"start it first (README: Connect your ROS stack)") from None
            raise
        try:
            sock.settimeout(HANDSHAKE_TIMEOUT)
            destination, payload = read_frame(sock)
            if destination != "__handshake":
                raise ValueError(f"the first message was {destination!r}, not __handshake")
            version, protocol = _greeting(payload)
        except (OSError, ValueError, ConnectionError) as exc:
            sock.close()
            if first:
                raise UserError(f"--ros-tcp: {where} did not greet as a ROS-TCP-Endpoint ({exc})") from None
            raise ConnectionError(str(exc)) from None
        if self.protocol is not None and protocol != self.protocol:
            sock.close()
            raise ConnectionError(f"the endpoint at {where} now speaks {protocol}, not {self.protocol}")
        sock.settimeout(None)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._sock_lock:  # (close() may have run meanwhile: then this connection is not kept)
            if self._closing.is_set():
                sock.close()
                raise ConnectionError("closing")
            self.version, self.protocol = version, protocol
            self.sock = sock
        for topic, (typename, _) in list(self._subs.items()):  # (copies: the main thread may be adding topics)
            self._command("__subscribe", {"topic": topic, "message_name": typename.replace("/msg/", "/")})
        for topic, typename in list(self._pubs.items()):
            self._command("__publish", {"topic": topic, "message_name": typename.replace("/msg/", "/"),
                                        "queue_size": 10, "latch": False})

    def _send(self, data: bytes) -> None:
        sock = self.sock
        if sock is None:
            self.dropped += 1
            return
        with self._send_lock:
            try:
                sock.sendall(data)
            except OSError:
                self.dropped += 1   # the reader notices the broken connection and reconnects

    def _command(self, name: str, params: dict) -> None:
        text = json.dumps(params) + ("\x00" if self.protocol == "ROS2" else "")
        self._send(frame(name, text.encode("utf-8")))

    def _read_loop(self) -> None:
        while not self._closing.is_set():
            sock = self.sock
            try:
                if sock is None:
                    raise ConnectionError("not connected")
                destination, payload = read_frame(sock)
            except (OSError, ConnectionError) as exc:
                if self._closing.is_set():
                    return
                self.sock = None
                if sock is not None:
                    sock.close()
                    self._log(("tcp", "lost"), f"ros-tcp: lost the endpoint at {self.host}:{self.port} ({exc}); "
                                               f"reconnecting every {RECONNECT_INTERVAL:g} s")
                if self._closing.wait(RECONNECT_INTERVAL):
                    return
                try:
                    self._connect(HANDSHAKE_TIMEOUT)
                    self._log(("tcp", "reconnected"), f"ros-tcp: reconnected to {self.host}:{self.port}")
                except (OSError, ConnectionError):
                    pass
                continue
            try:
                if destination.startswith("__"):
                    self._system(destination, payload)
                elif destination:
                    sub = self._subs.get(destination)
                    if sub is not None:
                        sub[1](payload)
            except Exception as exc:  # noqa: BLE001 - a message this client cannot take must not end its input
                self._log(("tcp", "unreadable", destination[:80]),
                          f"ros-tcp: ignored a message to {destination[:80]!r} that could not be read "
                          f"({type(exc).__name__}: {exc})")

    def _system(self, destination: str, payload: bytes) -> None:
        if destination in ("__error", "__warn", "__log"):
            try:
                said = json.loads(payload.decode("utf-8").rstrip("\x00"))
                text = str(said.get("text", "")) if isinstance(said, dict) else str(said)[:200]
            except ValueError:
                text = payload[:200].decode("utf-8", "replace")
            if destination != "__log":
                self._log(("tcp", text), f"ros-tcp endpoint {destination[2:]}: {text}")

    # ------------------------------------------------------------------------------------------ transport
    def advertise(self, topic: str, typename: str) -> None:
        self._pubs[topic] = typename
        self._command("__publish", {"topic": topic, "message_name": typename.replace("/msg/", "/"),
                                    "queue_size": 10, "latch": False})

    def subscribe(self, topic: str, typename: str, on_bytes) -> None:
        self._subs[topic] = (typename, on_bytes)
        self._command("__subscribe", {"topic": topic, "message_name": typename.replace("/msg/", "/")})

    def publish(self, topic: str, data: bytes) -> None:
        self._send(frame(topic, data))

    def close(self) -> None:
        self._closing.set()
        with self._sock_lock:
            sock, self.sock = self.sock, None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
        self._reader.join(timeout=5.0)
