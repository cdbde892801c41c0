"""A simulated strobe controller that speaks the real protocol, with fault injection.

:class:`SimulatedStrobeController` is a pure state machine on a clock: feed it the
host's bytes with :meth:`~SimulatedStrobeController.feed`, collect the bytes it sends
back with :meth:`~SimulatedStrobeController.poll`. It shares framing, CRC and
message packing with the driver (:mod:`mifacerf.capture.hardware.protocol`). The
transports that carry it over a real pseudo-terminal or an in-process port object
live in :mod:`mifacerf.capture.simulation.transport`.

Faults (:class:`Faults`, all seeded): replies and events dropped, garbled (one bit
flipped, the CRC catches it) or delayed, line noise between frames, strobes that
fail to fire (the EVENT says so), strobes that never fire, the device resetting
mid-sequence (it loses its sequence and announces a new ``boot_id``), and a device
that stops answering altogether.

Listeners (e.g. the synthetic cameras) are told about every camera trigger with the
light that actually lit the subject, so simulated images match what the controller
reports, misfires included.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..hardware import protocol as P


@dataclass
class Faults:
    """Fault injection rates (probabilities) for the simulated controller.

    Per frame the device sends: ``drop`` (lost), ``garble`` (one bit flipped),
    ``delay`` (sent ``delay_s`` late), ``noise`` (random bytes sent before it).
    Per step: ``misfire`` (strobe does not fire; reported in its EVENT). Per RUN:
    ``reset`` (the device reboots at a random step). ``dead_strobes``: lights
    (indices) that never fire. ``silent_after``: the device stops answering after
    this many commands (None: never).
    """

    drop: float = 0.0
    garble: float = 0.0
    delay: float = 0.0
    delay_s: float = 2.0
    noise: float = 0.0
    misfire: float = 0.0
    reset: float = 0.0
    dead_strobes: tuple[int, ...] = ()
    silent_after: int | None = None
    seed: int = 0

    @classmethod
    def uniform(cls, rate: float, seed: int = 0) -> "Faults":
        """Every link fault at ``rate``, strobe misfires at ``rate``/4, resets at ``rate``·4 per run."""
        return cls(drop=rate, garble=rate, delay=rate / 4, delay_s=0.6, noise=rate, misfire=rate / 4,
                   reset=min(1.0, 4 * rate), seed=seed)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class Trigger:
    """One camera trigger as it happened: ``light`` is None when the strobe misfired."""

    boot_id: int
    trigger: int
    step: int
    light: int | None
    camera_mask: int
    time: float


@dataclass
class FaultCounts:
    dropped: int = 0
    garbled: int = 0
    delayed: int = 0
    noise: int = 0
    misfires: int = 0
    resets: int = 0
    replayed: int = 0


class SimulatedStrobeController:
    """The strobe controller of a light stage with ``n_positions`` arm positions and
    ``n_strobes`` strobes, on a clock in seconds.

    ``time_scale`` multiplies every duration (1: real time, 60 Hz; 0: instantaneous).
    """

    ROTATE_S_PER_POSITION = 0.05
    BOOT_S = 0.2

    def __init__(self, n_positions: int, n_strobes: int, n_cameras: int = 6, faults: Faults | None = None,
                 *, max_steps: int = 4096, time_scale: float = 0.0, boot_id: int = 1):
        self.n_positions, self.n_strobes, self.n_cameras = n_positions, n_strobes, n_cameras
        self.faults = faults or Faults()
        self.rng = np.random.default_rng(self.faults.seed)
        self.max_steps = max_steps
        self.time_scale = float(time_scale)
        self.listeners: list[Callable[[Trigger], None]] = []
        self.boot_listeners: list[Callable[[int], None]] = []
        self.counts = FaultCounts()
        self.commands_seen = 0
        self._decoder = P.FrameDecoder()
        self._out: list[tuple[float, int, bytes]] = []   # (due, order, bytes)
        self._order = 0
        self._timeline: list[tuple[float, int, Callable[[], None]]] = []
        self._boot(boot_id, announce=False, now=0.0)

    # ------------------------------------------------------------------ state
    def _boot(self, boot_id: int, announce: bool, now: float, reason=P.BootReason.POWER_ON) -> None:
        self.boot_id = boot_id
        self.state = P.State.IDLE
        self.arm = 0
        self.trigger_counter = 0
        self.steps: list[P.Step] = []
        self.log: list[P.Event] = []
        self.misfires = 0
        self.run_seq = 0
        self.steps_done = 0
        self._cache: dict[int, tuple[bytes, list[bytes]]] = {}
        self._timeline = []
        if announce:
            self._emit(P.encode_frame(0, P.Msg.BOOT, P.BOOT.pack(boot_id, int(reason))), now + self.BOOT_S * self.time_scale)
            for cb in self.boot_listeners:
                cb(boot_id)

    @property
    def silent(self) -> bool:
        f = self.faults.silent_after
        return f is not None and self.commands_seen > f

    # --------------------------------------------------------------- transport
    def feed(self, data: bytes, now: float) -> None:
        """Bytes from the host at time ``now``."""
        self.advance(now)
        for frame in self._decoder.feed(data):
            self.commands_seen += 1
            if self.silent:
                continue
            self._handle(frame, now)

    def poll(self, now: float) -> bytes:
        """Bytes the device has sent by time ``now``."""
        self.advance(now)
        if self.silent:
            self._out.clear()
            return b""
        self._out.sort()
        due = [o for o in self._out if o[0] <= now]
        self._out = [o for o in self._out if o[0] > now]
        return b"".join(o[2] for o in due)

    def next_due(self) -> float | None:
        """Time of the next thing the device will do or send (None: nothing pending)."""
        times = [t for t, _, _ in self._timeline] + [t for t, _, _ in self._out]
        return min(times) if times else None

    def advance(self, now: float) -> None:
        while self._timeline:
            self._timeline.sort(key=lambda e: (e[0], e[1]))
            t, _, action = self._timeline[0]
            if t > now:
                break
            self._timeline.pop(0)
            action()

    def _schedule(self, t: float, action: Callable[[], None]) -> None:
        self._order += 1
        self._timeline.append((t, self._order, action))

    def _emit(self, frame: bytes, due: float) -> None:
        """Queue one frame for sending, through the link faults."""
        f, rng = self.faults, self.rng
        if rng.random() < f.drop:
            self.counts.dropped += 1
            return
        if rng.random() < f.garble:
            self.counts.garbled += 1
            b = bytearray(frame)
            i = int(rng.integers(1, len(b)))  # never the SOF, so the frame is not simply skipped
            b[i] ^= 1 << int(rng.integers(8))
            frame = bytes(b)
        if rng.random() < f.delay:
            self.counts.delayed += 1
            due += f.delay_s
        if rng.random() < f.noise:
            self.counts.noise += 1
            frame = rng.integers(0, 256, int(rng.integers(1, 12)), dtype=np.uint8).tobytes() + frame
        self._order += 1
        self._out.append((due, self._order, frame))

    # ---------------------------------------------------------------- commands
    def _handle(self, frame: P.Frame, now: float) -> None:
        raw = frame.encode()
        cached = self._cache.get(frame.seq)
        if cached is not None and cached[0] == raw:  # a retry: replay, do not execute again
            self.counts.replayed += 1
            for b in cached[1]:
                self._emit(b, now)
            return
        replies: list[bytes] = []
        delay = 0.0

        def ack(data: bytes = b"") -> None:
            replies.append(P.encode_frame(frame.seq, P.Msg.ACK, bytes([frame.type]) + data))

        def nak(reason: P.Reason, text: str) -> None:
            replies.append(P.encode_frame(frame.seq, P.Msg.NAK, P.pack_nak(frame.type, reason, text)))

        try:
            msg = P.Msg(frame.type)
        except ValueError:
            msg = None
        try:
            if msg is P.Msg.HELLO:
                ack(P.HelloInfo(P.VERSION, self.n_positions, self.n_strobes, self.n_cameras,
                                self.max_steps, self.boot_id).pack())
            elif msg is P.Msg.STATUS:
                ack(P.StatusInfo(self.state, self.arm, self.boot_id, self.trigger_counter & 0xFFFFFFFF,
                                 len(self.steps), self.steps_done, min(self.misfires, 255)).pack())
            elif msg is P.Msg.ROTATE:
                (pos,) = struct.unpack("<H", frame.payload)
                if self.state is P.State.RUNNING:
                    nak(P.Reason.BUSY, "a sequence is running")
                elif pos >= self.n_positions:
                    nak(P.Reason.OUT_OF_RANGE, f"arm position {pos} >= {self.n_positions}")
                else:
                    delay = abs(pos - self.arm) * self.ROTATE_S_PER_POSITION * self.time_scale
                    self.arm = pos
                    ack(struct.pack("<H", pos))
            elif msg is P.Msg.LOAD:
                offset, steps = P.unpack_load(frame.payload)
                bad = [s for s in steps if s.arm_position >= self.n_positions or s.strobe >= self.n_strobes]
                if self.state is P.State.RUNNING:
                    nak(P.Reason.BUSY, "a sequence is running")
                elif offset not in (0, len(self.steps)):
                    nak(P.Reason.NOT_CONTIGUOUS, f"offset {offset}, but {len(self.steps)} steps are loaded")
                elif bad:
                    nak(P.Reason.OUT_OF_RANGE, f"step {bad[0]} outside {self.n_positions} positions x "
                                               f"{self.n_strobes} strobes")
                elif offset + len(steps) > self.max_steps:
                    nak(P.Reason.TOO_MANY_STEPS, f"{offset + len(steps)} steps > {self.max_steps}")
                else:
                    self.steps = self.steps[:offset] + steps
                    self.state = P.State.LOADED if self.steps else P.State.IDLE
                    ack(struct.pack("<H", len(self.steps)))
            elif msg is P.Msg.RUN:
                period_us, n = P.RUN.unpack(frame.payload)
                if self.state is P.State.RUNNING:
                    nak(P.Reason.BUSY, "a sequence is already running")
                elif not self.steps:
                    nak(P.Reason.NO_SEQUENCE, "no sequence loaded")
                elif n != len(self.steps):
                    nak(P.Reason.BAD_PAYLOAD, f"RUN asks for {n} steps, {len(self.steps)} are loaded")
                elif period_us < P.MIN_PERIOD_US:
                    nak(P.Reason.RATE_TOO_HIGH, f"period {period_us} us is shorter than the cameras' "
                                                f"{P.MIN_PERIOD_US} us (60 Hz)")
                else:
                    ack()
                    self._start_run(frame.seq, period_us, now)
            elif msg is P.Msg.ABORT:
                if self.state is P.State.RUNNING:
                    self._timeline = []
                    self._finish_run(now, aborted=True)
                ack()
            elif msg is P.Msg.CLEAR:
                if self.state is P.State.RUNNING:
                    nak(P.Reason.BUSY, "a sequence is running")
                else:
                    self.steps, self.state = [], P.State.IDLE
                    ack()
            elif msg is P.Msg.READLOG:
                first, count = P.READLOG.unpack(frame.payload)
                count = min(count, P.MAX_EVENTS_PER_READ)
                ack(P.pack_events(first, self.log[first:first + count]))
            else:
                nak(P.Reason.UNKNOWN_COMMAND, f"unknown command 0x{frame.type:02x}")
        except (struct.error, P.ProtocolError) as exc:
            replies = []
            nak(P.Reason.BAD_PAYLOAD, str(exc))
        self._cache[frame.seq] = (raw, replies)
        for b in replies:
            self._emit(b, now + delay)

    # ------------------------------------------------------------------- runs
    def _start_run(self, seq: int, period_us: int, now: float) -> None:
        self.state = P.State.RUNNING
        self.run_seq = seq
        self.log = []
        self.misfires = 0
        self.steps_done = 0
        period = period_us * 1e-6 * self.time_scale
        reset_at = None
        if self.rng.random() < self.faults.reset:
            reset_at = int(self.rng.integers(0, len(self.steps)))
        for i, step in enumerate(self.steps):
            t = now + (i + 1) * period
            if i == reset_at:
                self._schedule(t, lambda t=t: self._reset(t))
                return
            self._schedule(t, lambda i=i, t=t, t0=now: self._fire(i, t, t0))
        self._schedule(now + (len(self.steps) + 1) * period, lambda t=now + (len(self.steps) + 1) * period:
                       self._finish_run(t, aborted=False))

    def _fire(self, i: int, t: float, t0: float) -> None:
        step = self.steps[i]
        light = step.arm_position * self.n_strobes + step.strobe
        fired = light not in self.faults.dead_strobes and self.rng.random() >= self.faults.misfire
        if not fired:
            self.misfires += 1
            self.counts.misfires += 1
        self.arm = step.arm_position
        self.trigger_counter += 1
        scale = self.time_scale or 1.0
        ev = P.Event(i, self.trigger_counter & 0xFFFFFFFF, step.arm_position, step.strobe, fired,
                     int(round((t - t0) / scale * 1e6)) & 0xFFFFFFFF)
        self.log.append(ev)
        self.steps_done = i + 1
        trig = Trigger(self.boot_id, ev.trigger, i, light if fired else None, step.camera_mask, t)
        for cb in self.listeners:
            cb(trig)
        self._emit(P.encode_frame(self.run_seq, P.Msg.EVENT, ev.pack()), t)

    def _finish_run(self, t: float, aborted: bool) -> None:
        fired = sum(e.fired for e in self.log)
        self.state = P.State.LOADED if self.steps else P.State.IDLE
        self._emit(P.encode_frame(self.run_seq, P.Msg.DONE,
                                  P.Done(len(self.log), fired, len(self.log) - fired, aborted).pack()), t)

    def _reset(self, t: float) -> None:
        self.counts.resets += 1
        self._boot((self.boot_id + 1) & 0xFFFFFFFF, announce=True, now=t, reason=P.BootReason.WATCHDOG)
