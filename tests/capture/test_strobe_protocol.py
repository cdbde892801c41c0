"""The strobe controller's framing, CRC and message packing (pure bytes in, bytes out)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mifacerf.capture.hardware import protocol as P
from mifacerf.capture.hardware.sequence import Sequence, olat_sequence


def test_crc_check_values():
    # the published check values of CRC-16/CCITT-FALSE and CRC-8 (poly 0x07)
    assert P.crc16(b"123456789") == 0x29B1
    assert P.crc8(b"123456789") == 0xF4


def test_frame_layout_is_frozen():
    # the documented byte layout (docs/hardware.md); a change here breaks deployed controllers
    f = P.encode_frame(3, P.Msg.HELLO, b"abc")
    assert f.hex() == "a501030103000c616263419f"
    assert f[0] == P.SOF and f[1] == P.VERSION and f[2] == 3 and f[3] == P.Msg.HELLO
    assert int.from_bytes(f[4:6], "little") == 3
    assert f[6] == P.crc8(f[1:6])
    assert int.from_bytes(f[-2:], "little") == P.crc16(f[1:-2])


@settings(max_examples=60, deadline=None)
@given(frames=st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255), st.binary(max_size=64)), max_size=6),
       cuts=st.lists(st.integers(1, 40), max_size=8))
def test_round_trip_in_any_chunks(frames, cuts):
    data = b"".join(P.encode_frame(s, t, p) for s, t, p in frames)
    dec = P.FrameDecoder()
    out, pos = [], 0
    for c in cuts + [len(data)]:
        out += dec.feed(data[pos:pos + c])
        pos += c
    assert [(f.seq, f.type, f.payload) for f in out] == frames
    assert dec.crc_errors == 0


def test_decoder_resynchronises_after_noise_and_corruption():
    good = P.encode_frame(7, P.Msg.STATUS)
    bad = bytearray(P.encode_frame(8, P.Msg.ROTATE, b"\x01\x00"))
    bad[-1] ^= 0x10  # payload CRC wrong
    noise = bytes([0xA5, 0x01, 0x99, 0x12]) + b"\x00\xff" * 5
    out = P.decode_frames(noise + bytes(bad) + good)
    assert [(f.seq, f.type) for f in out] == [(7, P.Msg.STATUS)]


def test_corrupted_length_does_not_stall_the_decoder():
    # a flipped bit in the length would make a receiver wait for bytes that never come;
    # the header check rejects it at once so the next frame is decoded immediately
    first = bytearray(P.encode_frame(1, P.Msg.HELLO))
    first[5] ^= 0x02  # length high byte: 512 more bytes
    second = P.encode_frame(2, P.Msg.STATUS)
    dec = P.FrameDecoder()
    out = dec.feed(bytes(first) + second)
    assert [f.seq for f in out] == [2]


def test_payloads_round_trip_and_reject_bad_lengths():
    steps = [P.Step(1, 2, 0x3F), P.Step(0, 5)]
    off, back = P.unpack_load(P.pack_load(12, steps))
    assert off == 12 and back == steps
    ev = [P.Event(0, 10, 1, 2, True, 16666), P.Event(1, 11, 1, 3, False, 33333)]
    first, got = P.unpack_events(P.pack_events(4, ev))
    assert first == 4 and got == ev
    st_ = P.StatusInfo(P.State.RUNNING, 3, 9, 100, 12, 5, 1)
    assert P.StatusInfo.unpack(st_.pack()) == st_
    hello = P.HelloInfo(1, 16, 30, 6, 4096, 77)
    assert P.HelloInfo.unpack(hello.pack()) == hello
    d = P.Done(480, 478, 2, False)
    assert P.Done.unpack(d.pack()) == d
    with pytest.raises(P.ProtocolError):
        P.unpack_load(P.pack_load(0, steps)[:-1])
    with pytest.raises(P.ProtocolError):
        P.StatusInfo.unpack(st_.pack() + b"\x00")
    with pytest.raises(P.ProtocolError):
        P.Event.unpack(ev[0].pack()[:5])
    with pytest.raises(P.ProtocolError):
        P.encode_frame(256, P.Msg.HELLO)
    with pytest.raises(P.ProtocolError):
        P.encode_frame(1, P.Msg.HELLO, bytes(P.MAX_PAYLOAD + 1))
    cmd, reason, text = P.unpack_nak(P.pack_nak(P.Msg.RUN, P.Reason.NO_SEQUENCE, "no sequence loaded"))
    assert (cmd, reason, text) == (P.Msg.RUN, P.Reason.NO_SEQUENCE, "no sequence loaded")


def test_round_trip_through_pyserial_loop_port():
    import serial

    port = serial.serial_for_url("loop://", timeout=0.05)
    try:
        frames = [P.encode_frame(i, P.Msg.EVENT, P.Event(i, i, 0, i % 4, True, i).pack()) for i in range(20)]
        port.write(b"".join(frames))
        dec = P.FrameDecoder()
        got = dec.feed(port.read(10_000))
    finally:
        port.close()
    assert [P.Event.unpack(f.payload).step for f in got] == list(range(20))


# ------------------------------------------------------------------------------ sequences
def test_olat_sequence_order_and_plain_data():
    seq = olat_sequence(3, 4)
    assert len(seq) == 12
    # grouped by arm position; serpentine: position 1 runs bottom -> top
    assert [(s.arm_position, s.strobe) for s in seq.steps[:8]] == [(0, 0), (0, 1), (0, 2), (0, 3),
                                                                  (1, 3), (1, 2), (1, 1), (1, 0)]
    assert sorted(seq.lights.tolist()) == list(range(12))
    assert Sequence.from_dict(seq.to_dict()) == seq
    sub = olat_sequence(3, 4, lights=[11, 1, 5, 1])
    assert sub.lights.tolist() == [1, 5, 11]
    assert seq.duration_s == pytest.approx(12 / 60, rel=1e-3)


def test_sequence_rejects_bad_input():
    with pytest.raises(ValueError, match="60 Hz"):
        olat_sequence(2, 2, period_us=10_000)
    with pytest.raises(ValueError, match="light indices"):
        olat_sequence(2, 2, lights=[4])
    with pytest.raises(ValueError):
        olat_sequence(0, 2)
    assert len(olat_sequence(2, 2, lights=np.array([], np.int64))) == 0
