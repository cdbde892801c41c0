"""The strobe controller driver against the simulated controller: in-process, over a real
pseudo-terminal, over pyserial's loop://, and replaying a recorded transcript."""
import os
import time
from pathlib import Path

import pytest

from helpers.capture import scripted_exchange
from mifacerf.capture.hardware import protocol as P
from mifacerf.capture.hardware.controller import (CommandRefused, ControllerTimeout, DeviceReset, PortError,
                                                  StrobeController)
from mifacerf.capture.hardware.sequence import olat_sequence
from mifacerf.capture.simulation.device import Faults, SimulatedStrobeController
from mifacerf.capture.simulation.transport import PtySimulator, ReplayMismatch, ReplayPort, SimulatedPort

DATA = Path(__file__).parent / "data"


def make(faults=None, n_pos=4, n_str=4, timeout=0.05, **kw):
    dev = SimulatedStrobeController(n_pos, n_str, 2, faults or Faults(), **kw)
    return dev, StrobeController(SimulatedPort(dev), timeout=timeout)


def test_clean_run_reports_every_step_in_order():
    dev, ctl = make()
    info = ctl.hello()
    assert (info.n_positions, info.n_strobes, info.boot_id) == (4, 4, 1)
    seq = olat_sequence(4, 4)
    ctl.load(seq)
    res = ctl.run(seq)
    assert [e.step for e in res.events] == list(range(16))
    assert [(e.arm_position, e.strobe) for e in res.events] == [(s.arm_position, s.strobe) for s in seq.steps]
    assert all(e.fired for e in res.events) and res.done == P.Done(16, 16, 0, False)
    assert [e.trigger for e in res.events] == list(range(1, 17))
    assert ctl.stats.retries == 0
    st = ctl.status()
    assert st.state == P.State.LOADED and st.steps_done == 16 and st.trigger_counter == 16


def test_refused_commands_give_reasons_and_are_never_acknowledged():
    dev, ctl = make()
    ctl.hello()
    with pytest.raises(CommandRefused) as e:
        ctl.rotate(9)
    assert e.value.reason == P.Reason.OUT_OF_RANGE and "arm position 9" in str(e.value)
    with pytest.raises(CommandRefused) as e:
        ctl.run(olat_sequence(4, 4))
    assert e.value.reason == P.Reason.NO_SEQUENCE
    with pytest.raises(CommandRefused) as e:
        ctl.transact(P.Msg.LOAD, P.pack_load(0, [P.Step(7, 0)]))
    assert e.value.reason == P.Reason.OUT_OF_RANGE
    with pytest.raises(CommandRefused) as e:
        ctl.transact(P.Msg.RUN, P.RUN.pack(1000, 1))
    assert e.value.reason in (P.Reason.NO_SEQUENCE, P.Reason.RATE_TOO_HIGH)
    ctl.load(olat_sequence(4, 4, [0, 1]))
    with pytest.raises(CommandRefused) as e:
        ctl.transact(P.Msg.RUN, P.RUN.pack(1000, 2))
    assert e.value.reason == P.Reason.RATE_TOO_HIGH and "60 Hz" in e.value.text
    with pytest.raises(CommandRefused) as e:
        ctl.transact(0x33)
    assert e.value.reason == P.Reason.UNKNOWN_COMMAND
    # on the wire: exactly one reply per command, ACK or NAK, never both
    dev2 = SimulatedStrobeController(4, 4)
    for seq, cmd, payload in [(1, P.Msg.ROTATE, b"\x09\x00"), (2, P.Msg.ROTATE, b"\x01\x00"), (3, P.Msg.RUN, b"")]:
        dev2.feed(P.encode_frame(seq, cmd, payload), 0.0)
        replies = P.decode_frames(dev2.poll(10.0))
        assert len(replies) == 1 and replies[0].seq == seq and replies[0].type in (P.Msg.ACK, P.Msg.NAK)


def test_lossy_line_still_delivers_every_event_once():
    # a third of all frames dropped, garbled or preceded by noise: retries and READLOG recover
    dev, ctl = make(Faults(drop=0.12, garble=0.12, noise=0.12, seed=5))
    ctl.hello()
    for _ in range(5):
        seq = olat_sequence(4, 4)
        ctl.load(seq)
        res = ctl.run(seq)
        assert [e.step for e in res.events] == list(range(16))
    assert ctl.stats.retries > 0 and ctl.stats.crc_errors > 0 and ctl.stats.log_reads > 0
    assert dev.counts.replayed > 0  # retries were answered from the reply cache, not executed twice
    assert dev.trigger_counter == 5 * 16  # no RUN executed twice: exactly 80 flashes


def test_retried_load_is_not_executed_twice():
    dev, ctl = make(Faults(drop=0.5, seed=2))
    ctl.retries = 20
    ctl.hello()
    seq = olat_sequence(4, 4)
    ctl.load(seq)  # several LOAD frames, some re-sent: the device must hold exactly 16 steps
    assert len(dev.steps) == 16 and ctl.status().steps_loaded == 16


def test_misfires_are_reported_per_step():
    dev, ctl = make(Faults(dead_strobes=(5,)))
    ctl.hello()
    seq = olat_sequence(4, 4)
    ctl.load(seq)
    res = ctl.run(seq)
    bad = [e for e in res.events if not e.fired]
    assert [(e.arm_position * 4 + e.strobe) for e in bad] == [5]
    assert res.done.misfired == 1 and res.misfired_steps == [bad[0].step]


def test_device_reset_mid_sequence_raises_with_the_steps_that_fired():
    dev, ctl = make(Faults(reset=1.0, seed=3))
    ctl.hello()
    seq = olat_sequence(4, 4)
    ctl.load(seq)
    with pytest.raises(DeviceReset) as e:
        ctl.run(seq)
    assert e.value.old_boot == 1 and e.value.new_boot == 2
    fired = [ev.step for ev in e.value.events]
    assert fired == list(range(len(fired))) and len(fired) < 16
    assert ctl.hello().boot_id == 2 and dev.steps == []  # the device forgot its sequence


def test_reset_detected_when_the_boot_announcement_is_lost():
    dev, ctl = make(Faults(reset=1.0, seed=3))
    ctl.hello()
    seq = olat_sequence(4, 4)
    ctl.load(seq)
    real_emit = dev._emit

    def emit(frame, due):  # the BOOT announcement is lost on the line
        if frame[3] != P.Msg.BOOT:
            real_emit(frame, due)

    dev._emit = emit
    with pytest.raises(DeviceReset):  # found by STATUS after the events stop
        ctl.run(seq)
    assert dev.counts.resets == 1


def test_silent_device_times_out_with_a_clear_message():
    dev, ctl = make(Faults(silent_after=1))
    ctl.hello()
    t0 = time.monotonic()
    with pytest.raises(ControllerTimeout, match="stopped answering"):
        ctl.status()
    assert time.monotonic() - t0 < 2.0
    assert ctl.stats.retries == ctl.retries


def test_permanently_corrupt_replies_are_a_timeout_not_a_crash():
    dev, ctl = make(Faults(garble=1.0))
    with pytest.raises(ControllerTimeout):
        ctl.hello()
    assert ctl.stats.timeouts == ctl.retries + 1 and ctl.stats.crc_errors + ctl.stats.dropped_bytes > 0


def test_loopback_port_echo_is_ignored_and_times_out():
    # a loopback plug (or a dead device on a port that echoes): our own commands must not count as replies
    ctl = StrobeController("loop://", timeout=0.05, retries=1)
    with pytest.raises(ControllerTimeout):
        ctl.hello()
    ctl.close()


def test_nonexistent_port_is_a_clear_error():
    with pytest.raises(PortError, match="/dev/ttyDOES_NOT_EXIST") as e:
        StrobeController("/dev/ttyDOES_NOT_EXIST")
    assert "--simulate" in str(e.value)


def test_over_a_real_pseudo_terminal_with_faults_and_clean_up():
    dev = SimulatedStrobeController(4, 4, 2, Faults(drop=0.05, garble=0.05, noise=0.05, misfire=0.05, seed=9),
                                    time_scale=0.05)
    fds_before = set(os.listdir("/proc/self/fd"))
    with PtySimulator(dev) as sim:
        assert sim.url.startswith("/dev/")
        with StrobeController(sim.url, timeout=0.2) as ctl:  # opened by pyserial's serial_for_url
            ctl.hello()
            for _ in range(3):
                seq = olat_sequence(4, 4)
                ctl.load(seq)
                assert len(ctl.run(seq).events) == 16
        assert sim.error is None
        thread = sim._thread
    assert thread is not None and not thread.is_alive()
    assert set(os.listdir("/proc/self/fd")) <= fds_before


def test_replay_of_recorded_transcript_matches_byte_for_byte():
    """Regenerate with ``python tests/helpers/capture.py`` after an intended protocol change."""
    port = ReplayPort.load(DATA / "transcript_olat.jsonl")
    ctl = StrobeController(port, timeout=0.02, rotate_s=0.0)
    res = scripted_exchange(ctl)
    assert port.finished
    assert len(res.events) == 6 and ctl.stats.retries > 0  # the recording holds lost replies and re-sends
    # the recording (Faults(misfire=0.1, seed=11) in helpers.capture.record_transcript) holds two misfired
    # strobes and three events lost on the line and read back with READLOG: all reported as recorded
    assert res.misfired_steps == [4, 5] and res.done == P.Done(6, 4, 2, False)
    assert res.recovered == 3 and ctl.stats.log_reads == 1


def test_replay_fails_on_any_difference():
    port = ReplayPort.load(DATA / "transcript_olat.jsonl")
    ctl = StrobeController(port, timeout=0.02, rotate_s=0.0)
    with pytest.raises(ReplayMismatch):
        scripted_exchange(ctl, lights=(0, 1, 2, 5, 6, 8))  # one light different
