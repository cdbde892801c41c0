"""Carry the simulated strobe controller over a real pseudo-terminal or an in-process port.

* :class:`PtySimulator` opens a pseudo-terminal pair (``os.openpty``) and runs the
  device in a thread on the master side; the driver opens the slave's path
  (``/dev/pts/N``) through ``serial.serial_for_url`` like any serial port. Use it as
  a context manager: the thread is stopped and both descriptors closed on exit.
* :class:`SimulatedPort` is a pyserial-like port object (``read``, ``write``,
  ``timeout``, ``in_waiting``, ``reset_input_buffer``, ``close``) wired straight to
  the device, for fast unit tests without threads.
* :class:`RecordingPort` wraps any port and keeps a transcript of both directions;
  :class:`ReplayPort` plays a transcript back and fails on the first byte the host
  sends that differs from the recording (record-and-replay tests).
"""
from __future__ import annotations

import json
import os
import select
import threading
import time
import tty
from pathlib import Path

from .device import SimulatedStrobeController


class SimulatedPort:
    """A port object on which the simulated controller answers (no thread, real clock)."""

    def __init__(self, device: SimulatedStrobeController, timeout: float = 0.2):
        self.device = device
        self.timeout = timeout
        self.is_open = True
        self._t0 = time.monotonic()
        self._rx = bytearray()
        self.port = "simulated"

    def _now(self) -> float:
        return time.monotonic() - self._t0

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise OSError("port is closed")
        self.device.feed(bytes(data), self._now())
        return len(data)

    def _pump(self) -> None:
        self._rx += self.device.poll(self._now())

    @property
    def in_waiting(self) -> int:
        self._pump()
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        deadline = time.monotonic() + (self.timeout if self.timeout is not None else 1e9)
        while True:
            self._pump()
            if len(self._rx) >= size or time.monotonic() >= deadline:
                out = bytes(self._rx[:size])
                del self._rx[:size]
                return out
            nxt = self.device.next_due()
            wait = deadline - time.monotonic()
            if nxt is not None:
                wait = min(wait, max(0.0, nxt - self._now()))
            time.sleep(max(0.0005, min(wait, 0.02)))

    def reset_input_buffer(self) -> None:
        self._pump()
        self._rx.clear()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False


class PtySimulator:
    """The simulated controller behind a real pseudo-terminal; ``url`` is the port to open.

    ::

        with PtySimulator(SimulatedStrobeController(12, 12)) as sim:
            ctl = StrobeController(sim.url)
    """

    def __init__(self, device: SimulatedStrobeController):
        self.device = device
        self.url: str | None = None
        self._master = self._slave = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.lock = threading.Lock()

    def start(self) -> "PtySimulator":
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.url = os.ttyname(self._slave)
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name="strobe-controller-sim", daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        pending = bytearray()
        try:
            while not self._stop.is_set():
                now = time.monotonic() - self._t0
                with self.lock:
                    nxt = self.device.next_due()
                timeout = 0.02 if nxt is None else min(0.02, max(0.0, nxt - now))
                wlist = [self._master] if pending else []
                r, w, _ = select.select([self._master], wlist, [], timeout)
                now = time.monotonic() - self._t0
                if r:
                    try:
                        data = os.read(self._master, 4096)
                    except (BlockingIOError, InterruptedError):
                        data = b""
                    except OSError:  # EIO: no process has the slave open right now
                        data = b""
                        time.sleep(0.005)
                    if data:
                        with self.lock:
                            self.device.feed(data, now)
                with self.lock:
                    pending += self.device.poll(now)
                if pending:
                    try:
                        n = os.write(self._master, pending)
                        del pending[:n]
                    except (BlockingIOError, InterruptedError):
                        pass
        except BaseException as exc:  # noqa: BLE001 - reported through .error
            self.error = exc

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def __enter__(self) -> "PtySimulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class RecordingPort:
    """Wraps a port; ``transcript`` lists ``("tx"|"rx", bytes)`` in the order they passed."""

    def __init__(self, port):
        self.inner = port
        self.transcript: list[tuple[str, bytes]] = []

    def write(self, data: bytes) -> int:
        self.transcript.append(("tx", bytes(data)))
        return self.inner.write(data)

    def read(self, size: int = 1) -> bytes:
        data = self.inner.read(size)
        if data:
            self.transcript.append(("rx", bytes(data)))
        return data

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def save(self, path: str | os.PathLike) -> None:
        """Write the transcript as JSON lines ``{"dir": "tx"|"rx", "hex": ...}`` (rx chunks merged)."""
        merged: list[list] = []
        for d, b in self.transcript:
            if merged and merged[-1][0] == d == "rx":
                merged[-1][1] += b
            else:
                merged.append([d, bytearray(b)])
        Path(path).write_text("".join(json.dumps({"dir": d, "hex": bytes(b).hex()}) + "\n" for d, b in merged))


class ReplayMismatch(AssertionError):
    """The host sent something other than what the recording holds."""


class ReplayPort:
    """Plays a recorded transcript: every write must equal the next recorded ``tx`` exactly;
    reads return the recorded ``rx`` bytes that follow it. Fails on any mismatch."""

    def __init__(self, transcript: list[tuple[str, bytes]], timeout: float = 0.05):
        self.items = list(transcript)
        self.pos = 0
        self.timeout = timeout
        self.is_open = True
        self._rx = bytearray()
        self.port = "replay"

    @classmethod
    def load(cls, path: str | os.PathLike, **kw) -> "ReplayPort":
        items = []
        for line in Path(path).read_text().splitlines():
            d = json.loads(line)
            items.append((d["dir"], bytes.fromhex(d["hex"])))
        return cls(items, **kw)

    def _release_rx(self) -> None:
        while self.pos < len(self.items) and self.items[self.pos][0] == "rx":
            self._rx += self.items[self.pos][1]
            self.pos += 1

    def write(self, data: bytes) -> int:
        data = bytes(data)
        if self.pos >= len(self.items) or self.items[self.pos][0] != "tx":
            raise ReplayMismatch(f"host sent {data.hex()} after the end of the recorded commands "
                                 f"(item {self.pos})")
        want = self.items[self.pos][1]
        if data != want:
            raise ReplayMismatch(f"item {self.pos}: host sent {data.hex()}, recording has {want.hex()}")
        self.pos += 1
        self._release_rx()
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        if not self._rx:
            time.sleep(min(self.timeout or 0.0, 0.01))
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    @property
    def finished(self) -> bool:
        return self.pos >= len(self.items) and not self._rx

    def reset_input_buffer(self) -> None:
        self._rx.clear()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.is_open = False
