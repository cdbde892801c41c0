"""Driver for the light stage's strobe controller (protocol: :mod:`.protocol`, docs/hardware.md).

:class:`StrobeController` takes a port object (anything with pyserial's ``read``,
``write`` and ``timeout``) or a pyserial URL (``/dev/ttyUSB0``, ``loop://``,
``socket://host:port``, ``rfc2217://...``, a pseudo-terminal path), which it opens
with ``serial.serial_for_url`` — never ``serial.Serial`` directly.

Every command waits for its ACK or NAK. A lost or corrupt reply is a timeout; the
command is re-sent with the *same* sequence number, which the device answers from
its reply cache without executing it twice. Errors are specific and say what to do:

* :class:`PortError` — the port cannot be opened (does not exist, busy, no permission);
* :class:`ControllerTimeout` — no valid reply after all retries (device silent or line dead);
* :class:`CommandRefused` — the device answered NAK, with its reason;
* :class:`DeviceReset` — the device rebooted (new ``boot_id``): its sequence is gone;
* :class:`ControllerProtocolError` — a valid frame with nonsense in it.
"""
from __future__ import annotations

import logging
import struct
import time
from dataclasses import dataclass, field
from typing import Callable

from . import protocol as P
from .sequence import Sequence
from ...errors import MifacerfError

log = logging.getLogger(__name__)


class ControllerError(MifacerfError, RuntimeError):
    """Any failure talking to the strobe controller."""


class PortError(ControllerError):
    """The serial port could not be opened."""


class ControllerTimeout(ControllerError):
    """The controller did not answer (after retries)."""


class ControllerProtocolError(ControllerError):
    """The controller answered with a malformed or unexpected message."""


class CommandRefused(ControllerError):
    """The controller refused a command (NAK) — ``reason`` says why."""

    def __init__(self, command: str, reason, text: str):
        self.command, self.reason, self.text = command, reason, text
        r = reason.name if isinstance(reason, P.Reason) else f"reason {reason}"
        super().__init__(f"strobe controller refused {command}: {r} ({text})")


class DeviceReset(ControllerError):
    """The controller rebooted (its ``boot_id`` changed); ``events`` holds what fired before."""

    def __init__(self, message: str, old_boot: int | None, new_boot: int | None,
                 events: list[P.Event] | None = None):
        super().__init__(message)
        self.old_boot, self.new_boot = old_boot, new_boot
        self.events = events or []


@dataclass
class LinkStats:
    """What the driver had to put up with: re-sent commands, timeouts, CRC errors, noise bytes."""

    commands: int = 0
    retries: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    dropped_bytes: int = 0
    stale_frames: int = 0
    log_reads: int = 0

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class RunResult:
    """The outcome of one sequence run: one :class:`~.protocol.Event` per step, in order."""

    events: list[P.Event]
    done: P.Done | None = None
    recovered: int = 0  # events read back with READLOG after being lost on the line
    extra: dict = field(default_factory=dict)

    @property
    def misfired_steps(self) -> list[int]:
        return [e.step for e in self.events if not e.fired]


def _u16(data: bytes, what: str) -> int:
    if len(data) != 2:
        raise ControllerProtocolError(f"{what} reply: {len(data)} data bytes, expected 2")
    return struct.unpack("<H", data)[0]


def open_port(port, *, baudrate: int = 115200, timeout: float = 0.05):
    """A pyserial port for ``port`` (URL or path), or ``port`` itself if it is already a port object."""
    if not isinstance(port, (str, bytes)):
        return port
    import serial

    try:
        return serial.serial_for_url(port, baudrate=baudrate, timeout=timeout, write_timeout=2.0)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise PortError(f"cannot open the strobe controller's port {port!r}: {exc}. Check the cable and "
                        "the device name (ls /dev/tty*), or run with --simulate.") from exc


class StrobeController:
    """Talks to the strobe controller on ``port`` (a port object or a pyserial URL).

    ``timeout``: seconds to wait for each reply; ``retries``: re-sends after a timeout;
    ``rotate_s``: extra time a ROTATE may take (the arm moves before it answers).
    ``record``: optional callable ``(direction, frame)`` for logging every frame.
    """

    def __init__(self, port, *, timeout: float = 0.5, retries: int = 4, baudrate: int = 115200,
                 rotate_s: float = 2.0, record: Callable[[str, P.Frame], None] | None = None):
        self._owns_port = isinstance(port, (str, bytes))
        self.port = open_port(port, baudrate=baudrate)
        try:
            self.port.timeout = min(0.05, timeout)
        except Exception:  # noqa: BLE001 - some port objects have a fixed timeout
            pass
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.rotate_s = float(rotate_s)
        self.record = record
        self.stats = LinkStats()
        self._decoder = P.FrameDecoder()
        self._inbox: list[P.Frame] = []  # events that arrived while waiting for a reply
        self._rxq: list[P.Frame] = []    # frames read but not yet looked at
        self._seq = 0
        self.boot_id: int | None = None
        self.info: P.HelloInfo | None = None
        self._boot_seen: int | None = None

    # ------------------------------------------------------------ low level
    def close(self) -> None:
        if self._owns_port:
            try:
                self.port.close()
            except Exception:  # noqa: BLE001
                pass

    def __enter__(self) -> "StrobeController":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _next_seq(self) -> int:
        self._seq = self._seq % 255 + 1  # 1..255; 0 is the device's unsolicited BOOT
        return self._seq

    def _read_frames(self, wait: float) -> list[P.Frame]:
        """Frames from the device (replies and events) arriving within ``wait`` seconds;
        returns as soon as at least one is complete."""
        if self._rxq:
            out, self._rxq = self._rxq, []
            return out
        deadline = time.monotonic() + wait
        while True:
            try:
                n = max(1, getattr(self.port, "in_waiting", 0) or 0)
                data = self.port.read(n)
            except OSError as exc:  # pyserial's SerialException is an OSError
                raise ControllerError(f"reading from the strobe controller failed: {exc}") from exc
            frames = []
            if data:
                before = (self._decoder.crc_errors, self._decoder.dropped_bytes)
                frames = self._decoder.feed(data)
                self.stats.crc_errors += self._decoder.crc_errors - before[0]
                self.stats.dropped_bytes += self._decoder.dropped_bytes - before[1]
            for f in frames:
                if self.record:
                    self.record("rx", f)
                if f.type == P.Msg.BOOT:
                    self._note_boot(f)
            frames = [f for f in frames if f.type >= 0x80 and f.type != P.Msg.BOOT]  # a loopback echoes commands
            if frames or time.monotonic() >= deadline:
                return frames

    def _note_boot(self, f: P.Frame) -> None:
        try:
            boot_id, reason = P.BOOT.unpack(f.payload)
        except struct.error:
            return
        if self.boot_id is not None and boot_id != self.boot_id:
            self._boot_seen = boot_id
            log.warning("strobe controller rebooted (boot %s -> %s, reason %s)", self.boot_id, boot_id, reason)

    def _check_reset(self, events=None) -> None:
        if self._boot_seen is not None:
            old, new = self.boot_id, self._boot_seen
            self._boot_seen = None
            self.boot_id = new
            raise DeviceReset(f"the strobe controller reset (boot {old} -> {new}); its sequence is lost",
                              old, new, events)

    def _send(self, frame: bytes) -> None:
        try:
            self.port.write(frame)
            if hasattr(self.port, "flush"):
                self.port.flush()
        except OSError as exc:  # pyserial's SerialException is an OSError
            raise ControllerError(f"writing to the strobe controller failed: {exc}") from exc

    def transact(self, command: P.Msg, payload: bytes = b"", *, timeout: float | None = None) -> bytes:
        """Send ``command``; return the ACK's data (after the echoed command byte).

        Retries on timeout with the same sequence number; raises :class:`CommandRefused`
        on NAK, :class:`ControllerTimeout` when every try went unanswered.
        """
        cname = P.name_of(command)
        seq = self._next_seq()
        raw = P.encode_frame(seq, command, payload)
        wait = self.timeout if timeout is None else timeout
        self.stats.commands += 1
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats.retries += 1
                log.info("no reply to %s #%d, re-sending (try %d)", cname, seq, attempt + 1)
            if self.record:
                self.record("tx", P.Frame(seq, command, payload))
            self._send(raw)
            deadline = time.monotonic() + wait
            while time.monotonic() < deadline:
                frames = self._read_frames(deadline - time.monotonic())
                while frames:
                    f = frames.pop(0)
                    if f.seq != seq or f.type not in (P.Msg.ACK, P.Msg.NAK):
                        if f.type in (P.Msg.EVENT, P.Msg.DONE):
                            self._inbox.append(f)
                        else:
                            self.stats.stale_frames += 1
                        continue
                    self._rxq = frames + self._rxq  # keep what came after the reply
                    if not f.payload or f.payload[0] != command:
                        raise ControllerProtocolError(
                            f"reply #{seq} acknowledges command {f.payload[:1].hex() or 'nothing'}, "
                            f"not {cname}")
                    if f.type == P.Msg.NAK:
                        self._check_reset()  # a refusal by a device that just rebooted is a reset
                        _, reason, text = P.unpack_nak(f.payload)
                        if reason in (P.Reason.NO_SEQUENCE, P.Reason.NOT_CONTIGUOUS) and self.boot_id is not None \
                                and command != P.Msg.STATUS:
                            self.status()  # the sequence vanished: did the device reset? (raises DeviceReset)
                        raise CommandRefused(cname, reason, text)
                    return f.payload[1:]
            self.stats.timeouts += 1
        raise ControllerTimeout(
            f"no valid reply from the strobe controller on {getattr(self.port, 'port', self.port)!r} to "
            f"{cname} after {self.retries + 1} tries of {wait:.2f} s: the device stopped answering "
            "or the line is dead (check power and cable)")

    # ----------------------------------------------------------- commands
    def hello(self) -> P.HelloInfo:
        """Identify the device; remembers its ``boot_id`` (a later change means it reset)."""
        try:
            info = P.HelloInfo.unpack(self.transact(P.Msg.HELLO))
        except P.ProtocolError as exc:
            raise ControllerProtocolError(str(exc)) from exc
        if info.protocol != P.VERSION:
            raise ControllerProtocolError(f"controller speaks protocol {info.protocol}, this driver {P.VERSION}")
        self.info = info
        self._boot_seen = None
        self.boot_id = info.boot_id
        return info

    def status(self) -> P.StatusInfo:
        """The device state; raises :class:`DeviceReset` if its ``boot_id`` changed."""
        try:
            st = P.StatusInfo.unpack(self.transact(P.Msg.STATUS))
        except P.ProtocolError as exc:
            raise ControllerProtocolError(str(exc)) from exc
        if self.boot_id is not None and st.boot_id != self.boot_id:
            self._boot_seen = st.boot_id
        self._check_reset()
        return st

    def rotate(self, arm_position: int) -> int:
        pos = _u16(self.transact(P.Msg.ROTATE, struct.pack("<H", arm_position), timeout=self.timeout + self.rotate_s),
                   "ROTATE")
        self._check_reset()
        return pos

    def clear(self) -> None:
        self.transact(P.Msg.CLEAR)

    def abort(self) -> None:
        self.transact(P.Msg.ABORT)

    def load(self, sequence: Sequence) -> None:
        """Upload ``sequence`` in LOAD frames; checks the device holds exactly its steps."""
        steps = sequence.steps
        if not steps:
            raise ValueError("cannot load an empty sequence")
        if self.info is not None and len(steps) > self.info.max_steps:
            raise ValueError(f"sequence of {len(steps)} steps exceeds the controller's {self.info.max_steps}")
        chunk = P.MAX_STEPS_PER_LOAD
        loaded = 0
        for off in range(0, len(steps), chunk):
            loaded = _u16(self.transact(P.Msg.LOAD, P.pack_load(off, steps[off:off + chunk])), "LOAD")
            self._check_reset()
        if loaded != len(steps):
            raise ControllerProtocolError(f"controller holds {loaded} steps after loading {len(steps)}")

    def run(self, sequence: Sequence, on_event: Callable[[P.Event], None] | None = None) -> RunResult:
        """Run the loaded ``sequence`` (which :meth:`load` sent) and wait for it to finish.

        Returns one event per step. Events lost on the line are read back with
        READLOG. Raises :class:`DeviceReset` (with the events that did fire) if the
        device rebooted during the run.
        """
        n = len(sequence)
        self._inbox = []
        self.transact(P.Msg.RUN, P.RUN.pack(sequence.period_us, n))
        run_seq = self._seq
        events: dict[int, P.Event] = {}
        done: P.Done | None = None
        period = sequence.period_us * 1e-6
        gap = self.timeout + 3 * period  # silence longer than this: ask the device how it is doing
        stall_limit = max(2.0, 10 * self.timeout)  # RUNNING without progress this long: give up
        last_progress = last_heard = time.monotonic()
        last_done_steps = -1
        pending = list(self._inbox)
        self._inbox = []
        while done is None:
            frames = pending or self._read_frames(min(0.05, gap))
            pending = []
            for f in frames:
                if f.seq != run_seq:
                    self.stats.stale_frames += 1
                    continue
                if f.type == P.Msg.EVENT:
                    try:
                        ev = P.Event.unpack(f.payload)
                    except P.ProtocolError as exc:
                        raise ControllerProtocolError(str(exc)) from exc
                    if ev.step < n and ev.step not in events:
                        events[ev.step] = ev
                        last_progress = last_heard = time.monotonic()
                        if on_event:
                            on_event(ev)
                elif f.type == P.Msg.DONE:
                    try:
                        done = P.Done.unpack(f.payload)
                    except P.ProtocolError as exc:
                        raise ControllerProtocolError(str(exc)) from exc
            if self._boot_seen is not None:
                self._check_reset(sorted(events.values(), key=lambda e: e.step))
            if done is None and time.monotonic() - last_heard > gap:
                # events or DONE lost, or the device reset / died: ask it (raises DeviceReset, ControllerTimeout)
                st = self.status()
                last_heard = time.monotonic()
                if st.state != P.State.RUNNING:
                    done = P.Done(st.steps_done, st.steps_done - st.misfires, st.misfires, st.steps_done < n)
                elif st.steps_done != last_done_steps:
                    last_done_steps, last_progress = st.steps_done, time.monotonic()
                elif time.monotonic() - last_progress > stall_limit:
                    raise ControllerTimeout(f"the strobe controller reports RUNNING but made no progress for "
                                            f"{stall_limit:.1f} s ({st.steps_done}/{n} steps)")
        recovered = 0
        missing = [i for i in range(min(done.steps, n)) if i not in events]
        while missing:
            first = missing[0]
            count = min(P.MAX_EVENTS_PER_READ, missing[-1] - first + 1)
            self.stats.log_reads += 1
            try:
                got_first, got = P.unpack_events(self.transact(P.Msg.READLOG, P.READLOG.pack(first, count)))
            except P.ProtocolError as exc:
                raise ControllerProtocolError(str(exc)) from exc
            self._check_reset(sorted(events.values(), key=lambda e: e.step))
            if got_first != first or not got:
                raise ControllerProtocolError(f"READLOG from step {first} returned {len(got)} events from {got_first}")
            for ev in got:
                if ev.step not in events:
                    events[ev.step] = ev
                    recovered += 1
                    if on_event:
                        on_event(ev)
            missing = [i for i in missing if i not in events]
        evs = [events[i] for i in sorted(events)]
        if done.aborted or len(evs) != n:
            raise ControllerError(f"sequence ended after {len(evs)} of {n} steps (aborted={done.aborted})")
        return RunResult(evs, done, recovered)
