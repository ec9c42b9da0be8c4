"""Serving a simulated device on a pseudo terminal or a loopback socket, and fault injection.

A simulator runs in threads: one per pseudo terminal, or an accept loop plus one per socket
connection.  Each connection is a :class:`Link` (read with a timeout, write, close); the
device's physical state is shared between connections and evolves with real time
(x ``time_scale``).
"""

from __future__ import annotations

import os
import select
import socket
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from urllib.parse import urlparse

FAULT_KINDS = ("no_reply", "late_reply", "garbage", "drop", "error_reply", "stall", "wrong_position")


@dataclass
class Fault:
    """One injected fault.

    kind : no_reply | late_reply | garbage | drop | error_reply | stall | wrong_position
        (drop closes a socket connection -- the client may reconnect; a pty cannot be dropped, so
        there the command is lost as with no_reply.  stall: a wheel that never gives the prompt,
        a stage that stops halfway with its moving bit set until told to stop.)
    on : which command it hits: ``"*"`` (any), an FW102C command prefix (``"pos="``, ``"pos?"``)
        or an APT message name or id (``"MOT_MOVE_ABSOLUTE"``, ``"0x0453"``).
    count : how many times it fires (0: every time).
    after : let this many matching commands through first.
    delay_s : late_reply: how late (s, not scaled); stall: how long the device hangs (0: until stopped).
    offset : wrong_position: how far off (wheel positions, or mm for the stage).
    """

    kind: str
    on: str = "*"
    count: int = 1
    after: int = 0
    delay_s: float = 0.0
    offset: float = 1.0
    fired: int = field(default=0, init=False)
    seen: int = field(default=0, init=False)

    def __post_init__(self):
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {self.kind!r}; one of {', '.join(FAULT_KINDS)}")


class Faults:
    """The faults armed on a simulator; thread-safe."""

    def __init__(self, faults=None):
        self._lock = threading.Lock()
        self._faults: list[Fault] = []
        for f in faults or ():
            self.add(**(f if isinstance(f, dict) else dict(f)))

    def add(self, kind: str, on: str = "*", count: int = 1, after: int = 0, delay_s: float = 0.0,
            offset: float = 1.0) -> Fault:
        f = Fault(kind, on, count, after, delay_s, offset)
        with self._lock:
            self._faults.append(f)
        return f

    def clear(self) -> None:
        with self._lock:
            self._faults.clear()

    def take(self, names: tuple[str, ...], kinds: tuple[str, ...] = FAULT_KINDS) -> Fault | None:
        """The first armed fault of one of ``kinds`` matching a command known by ``names``; counts it as fired."""
        with self._lock:
            for f in self._faults:
                if f.kind not in kinds or (f.count and f.fired >= f.count):
                    continue
                if f.on != "*" and not any(n.lower().startswith(f.on.lower()) for n in names):
                    continue
                f.seen += 1
                if f.seen <= f.after:
                    continue
                f.fired += 1
                return f
        return None


class Link:
    """One connection to the device (the simulator's side of the wire)."""

    def __init__(self, read_fd_or_sock, kind: str):
        self._io = read_fd_or_sock
        self.kind = kind
        self.closed = False
        self.fresh = True  # nothing received yet (a device may greet its first command differently)
        self.wlock = threading.Lock()

    def read(self, timeout_s: float) -> bytes:
        """Bytes available within ``timeout_s`` (b"" on timeout); sets ``closed`` when the peer went away."""
        if self.closed:
            return b""
        try:
            ready, _, _ = select.select([self._io], [], [], timeout_s)
            if not ready:
                return b""
            data = os.read(self._io, 4096) if self.kind == "pty" else self._io.recv(4096)
        except (OSError, ValueError):
            data = b""
        if not data:
            if self.kind == "socket":
                self.closed = True
            else:
                time.sleep(timeout_s)  # pty with no reader: nothing to do
        return data

    def write(self, data: bytes) -> None:
        if self.closed or not data:
            return
        try:
            with self.wlock:
                if self.kind == "pty":
                    view = memoryview(data)
                    while view:
                        try:
                            n = os.write(self._io, view)
                        except BlockingIOError:
                            return  # nobody reads the pty and its buffer is full: the bytes are lost, as on a wire
                        view = view[n:]
                else:
                    self._io.sendall(data)
        except OSError:
            if self.kind == "socket":
                self.closed = True

    def close(self) -> None:
        """Drop the connection (socket); a pty cannot be dropped and stays."""
        if self.kind == "socket" and not self.closed:
            self.closed = True
            try:
                self._io.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._io.close()


class SerialSimulator:
    """Base of the simulators: ``start(url)`` serves the device, ``stop()`` ends it.

    Subclasses implement :meth:`serve(link)`, the loop of one connection, which must return
    soon after ``self._stop`` is set or ``link.closed`` becomes true.
    """

    name = "device"

    def __init__(self, *, time_scale: float = 1.0, faults=None):
        if time_scale <= 0:
            raise ValueError("time_scale must be positive")
        self.time_scale = float(time_scale)
        self.faults = faults if isinstance(faults, Faults) else Faults(faults)
        self.url: str | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._links: list[Link] = []
        self._listener: socket.socket | None = None
        self._pty_fds: tuple[int, int] | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self, url: str = "pty") -> str:
        """Serve on ``"pty"`` (a new pseudo terminal: its slave path is returned) or
        ``"socket://HOST:PORT"`` (PORT 0: any free port; the actual URL is returned)."""
        if self.url is not None:
            raise RuntimeError(f"{self.name} simulator already serving on {self.url}")
        self._stop.clear()
        if url == "pty":
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no \r -> \n translation: the bytes go through as sent
            attrs = termios.tcgetattr(slave)
            termios.tcsetattr(slave, termios.TCSANOW, attrs)
            os.set_blocking(master, False)  # a full pty (no reader) must not block the device
            self._pty_fds = (master, slave)  # keep the slave open: a client closing it must not kill the master
            self.url = os.ttyname(slave)
            link = Link(master, "pty")
            self._links.append(link)
            self._spawn(self._serve_link, link)
        elif url.startswith("socket://"):
            parsed = urlparse(url)
            host, port = parsed.hostname or "127.0.0.1", parsed.port or 0
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(4)
            sock.settimeout(0.05)
            self._listener = sock
            self.url = f"socket://{host}:{sock.getsockname()[1]}"
            self._spawn(self._accept_loop)
        else:
            raise ValueError(f"{self.name} simulator: url must be 'pty' or 'socket://HOST:PORT', not {url!r}")
        return self.url

    def stop(self) -> None:
        """Stop serving; close every connection.  Safe to call twice."""
        self._stop.set()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        for link in list(self._links):
            link.close()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        self._links.clear()
        if self._pty_fds is not None:
            for fd in self._pty_fds:
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._pty_fds = None
        self.url = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def _spawn(self, target, *args) -> None:
        t = threading.Thread(target=target, args=args, daemon=True, name=f"{self.name}-sim")
        t.start()
        self._threads.append(t)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except (socket.timeout, OSError, AttributeError):
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            link = Link(conn, "socket")
            self._links.append(link)
            self._spawn(self._serve_link, link)

    def _serve_link(self, link: Link) -> None:
        try:
            self.serve(link)
        finally:
            link.close()
            if link in self._links:
                self._links.remove(link)

    # ------------------------------------------------------------------ helpers for subclasses
    def serve(self, link: Link) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def sleep(self, seconds: float) -> bool:
        """Sleep unless stopped; False when the simulator was stopped meanwhile."""
        return not self._stop.wait(max(0.0, seconds))

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def line_fault(self, link: Link, names: tuple[str, ...], kinds: tuple[str, ...] = ()) -> tuple[bool, Fault | None]:
        """Apply the line faults armed for a command known by ``names`` (no_reply, drop, late_reply,
        garbage), and take one of the device's own ``kinds``.  Returns ``(go_on, fault)``: go_on is
        False when the command is lost (no reply, dropped, or stopped meanwhile)."""
        fault = self.faults.take(names, ("no_reply", "late_reply", "garbage", "drop") + kinds)
        if fault is None:
            return True, None
        if fault.kind == "no_reply":
            return False, fault
        if fault.kind == "drop":  # a socket is closed; a pty cannot be dropped: the command is lost
            link.close()
            return False, fault
        if fault.kind == "late_reply" and not self.sleep(fault.delay_s):
            return False, fault
        if fault.kind == "garbage":
            link.write(garbage_bytes())
        return True, fault


def garbage_bytes(n: int = 7) -> bytes:
    """Line noise: bytes that are neither printable ASCII nor line ends."""
    return bytes((0x80 + (i * 37) % 0x7F) for i in range(n))
