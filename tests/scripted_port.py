"""A pyserial stand-in replaying a recorded conversation (PyMeasure's ``expected_protocol`` idea).

Each ``write`` must be exactly the next expected command (bytes); the device's reply to it then
becomes readable.  ``reset_input_buffer`` drops only what was already readable, as on a real
port where the reply has not arrived yet when the host flushes.
"""

from __future__ import annotations


class ScriptedPort:
    port = "scripted://wire"

    def __init__(self, conversation, *, initial: bytes = b""):
        self.conversation = [(bytes(w), bytes(r)) for w, r in conversation]
        self._rx = bytearray(initial)
        self.written: list[bytes] = []
        self.is_open = True
        self.timeout = 0

    # the part of the pyserial API the drivers use
    def write(self, data: bytes) -> int:
        data = bytes(data)
        self.written.append(data)
        assert self.conversation, f"unexpected write {data!r}: the recorded conversation is over"
        expected, reply = self.conversation.pop(0)
        assert data == expected, f"wrote {data!r}, the recording expects {expected!r}"
        self._rx += reply
        return len(data)

    def read(self, size: int = 1) -> bytes:
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def reset_input_buffer(self) -> None:
        self._rx.clear()

    def close(self) -> None:
        self.is_open = False

    def open(self) -> None:
        self.is_open = True

    def assert_done(self) -> None:
        assert not self.conversation, f"commands never sent: {[w for w, _ in self.conversation]}"
