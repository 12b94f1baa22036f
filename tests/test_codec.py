"""LSC codec: published byte vectors, round trips, value checks, streaming resynchronisation.

Byte vectors: the Hiwonder LSC-series communication protocol sheet's examples, copied into
docs/device.md, "Test vectors".
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crs_study.device import codec
from crs_study.device.codec import (
    ActionGroupComplete,
    ActionGroupRun,
    ActionGroupRunning,
    ActionGroupSpeed,
    ActionGroupStop,
    ActionGroupStopped,
    BatteryVoltage,
    Direction,
    GetBatteryVoltage,
    MultServoPosRead,
    MultServoUnload,
    ServoMove,
    ServoPositions,
)
from crs_study.device.decoder import FrameDecoder, decode_all, decode_frame
from crs_study.errors import DeviceError

VECTOR_ONE_SERVO = bytes.fromhex("55 55 08 03 01 E8 03 01 D0 07")  # servo 1 -> 2000 in 1000 ms
VECTOR_TWO_SERVOS = bytes.fromhex("55 55 0B 03 02 20 03 02 B0 04 09 FC 08")  # 2 -> 1200, 9 -> 2300
VECTOR_BATTERY = bytes.fromhex("55 55 04 0F 4C 1D")  # 7500 mV


def test_published_servo_move_vectors_encode_exactly():
    assert codec.servo_move({1: 2000}, 1000) == VECTOR_ONE_SERVO
    assert codec.servo_move([(2, 1200), (9, 2300)], 800) == VECTOR_TWO_SERVOS


def test_published_servo_move_vectors_decode_exactly():
    assert decode_frame(VECTOR_ONE_SERVO) == ServoMove(((1, 2000),), 1000)
    assert decode_frame(VECTOR_TWO_SERVOS) == ServoMove(((2, 1200), (9, 2300)), 800)


def test_published_battery_reply_decodes_to_7500_mv():
    assert decode_frame(VECTOR_BATTERY, "board") == BatteryVoltage(7500)
    assert codec.battery_voltage_reply(7500) == VECTOR_BATTERY


def test_fixed_frames_match_the_protocol_table():
    # docs/device.md table: Length 5 / 2 / 5 / 2, n + 3
    assert codec.action_group_run(3, 0) == bytes.fromhex("55 55 05 06 03 00 00")
    assert codec.action_group_stop() == bytes.fromhex("55 55 02 07")
    assert codec.action_group_speed(0xFF, 150) == bytes.fromhex("55 55 05 0B FF 96 00")
    assert codec.get_battery_voltage() == bytes.fromhex("55 55 02 0F")
    assert codec.mult_servo_unload([1, 2, 3]) == bytes.fromhex("55 55 06 14 03 01 02 03")
    assert codec.mult_servo_pos_read([4]) == bytes.fromhex("55 55 04 15 01 04")
    # position reply: Length 3n + 3
    assert codec.servo_positions_reply({4: 1500}) == bytes.fromhex("55 55 06 15 01 04 DC 05")


def test_servo_move_accepts_numpy_integers():
    assert codec.servo_move({np.int64(1): np.int32(2000)}, np.int64(1000)) == VECTOR_ONE_SERVO


@pytest.mark.parametrize(
    ("make", "match"),
    [
        pytest.param(lambda: codec.servo_move({1: 499}, 100),
                     r"servo 1 pulse width.*500\.\.2500.*499", id="pulse-low"),
        pytest.param(lambda: codec.servo_move({1: 2501}, 100), r"500\.\.2500.*2501",
                     id="pulse-high"),
        pytest.param(lambda: codec.servo_move({1: 1500}, 30001), r"move time.*0\.\.30000.*30001",
                     id="time"),
        pytest.param(lambda: codec.servo_move({1: 1500}, -1), r"move time.*-1", id="time-neg"),
        pytest.param(lambda: codec.servo_move({}, 100), r"at least one servo", id="empty"),
        pytest.param(lambda: codec.servo_move([(1, 1500), (1, 1600)], 100), r"repeat",
                     id="dup-id"),
        pytest.param(lambda: codec.servo_move({33: 1500}, 100), r"servo id.*0\.\.32.*33",
                     id="id-range"),
        pytest.param(lambda: codec.servo_move({1: 1500.0}, 100), r"whole number.*1500\.0",
                     id="float-pulse"),
        pytest.param(lambda: codec.mult_servo_unload(range(256)), r"servo id", id="n>255"),
        pytest.param(lambda: codec.action_group_run(256, 1), r"action group.*0\.\.255.*256",
                     id="group"),
        pytest.param(lambda: codec.action_group_run(1, 65536), r"repetitions.*65536", id="times"),
        pytest.param(lambda: codec.action_group_speed(1, -5), r"speed.*-5", id="speed"),
        pytest.param(lambda: codec.battery_voltage_reply(70000), r"battery.*70000", id="mv"),
        pytest.param(lambda: codec.servo_move({True: 1500}, 100), r"servo id.*True", id="bool"),
    ],
)
def test_invalid_values_raise_device_error(make, match):
    with pytest.raises(DeviceError, match=match):
        make()


def test_decode_frame_rejects_wrong_input():
    with pytest.raises(DeviceError, match="expected one frame"):
        decode_frame(VECTOR_ONE_SERVO[:-1])
    with pytest.raises(DeviceError, match="unknown command 0x42"):
        decode_frame(bytes.fromhex("55 55 02 42"))
    with pytest.raises(DeviceError, match="pulse width"):
        decode_frame(bytes.fromhex("55 55 08 03 01 E8 03 01 00 00"))


# ---------------------------------------------------------------------------------------------
# streaming decoder


def test_garbage_holding_a_header_is_skipped_and_the_next_frame_found():
    # garbage with 55 55 and an impossible command, then a real frame
    garbage = bytes.fromhex("00 55 55 09 42 13")
    frames, skipped = decode_all(garbage + VECTOR_ONE_SERVO)
    assert [f.raw for f in frames] == [VECTOR_ONE_SERVO]
    assert frames[0].offset == len(garbage)
    assert [(s.offset, s.data) for s in skipped] == [(0, garbage)]


def test_truncated_frame_followed_by_a_frame_resynchronises():
    # a frame cut off after 6 bytes, then complete frames: the stub swallows the next header,
    # its values are impossible (servo id 0x55), so the decoder drops it and finds the frames
    stream = VECTOR_ONE_SERVO[:6] + VECTOR_ONE_SERVO + VECTOR_TWO_SERVOS
    frames, skipped = decode_all(stream)
    assert [f.raw for f in frames] == [VECTOR_ONE_SERVO, VECTOR_TWO_SERVOS]
    assert [(s.offset, s.data) for s in skipped] == [(0, VECTOR_ONE_SERVO[:6])]


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        pytest.param("55 55 09 03", "bad length 9 for SERVO_MOVE", id="servo-move-length"),
        pytest.param("55 55 03 07", "bad length 3 for ACTION_GROUP_STOP", id="stop-length"),
        pytest.param("55 55 02 63", "unknown command 0x63", id="unknown"),
        pytest.param("55 55 0B 03 01 E8 03 01 D0 07 02 D0 07",
                     "servo count 1 does not match length 11", id="count-mismatch"),
    ],
)
def test_bad_lengths_and_unknown_commands_are_reported(bad, reason):
    frames, skipped = decode_all(bytes.fromhex(bad) + VECTOR_BATTERY + VECTOR_ONE_SERVO)
    assert [f.raw for f in frames] == [VECTOR_ONE_SERVO]  # battery reply is not a command
    assert skipped[0].offset == 0 and skipped[0].reason.startswith(reason)
    assert b"".join(s.data for s in skipped) == bytes.fromhex(bad) + VECTOR_BATTERY


def test_board_direction_reads_replies_and_notices():
    stream = (VECTOR_BATTERY + codec.servo_positions_reply({1: 1500, 2: 900})
              + ActionGroupRunning(2, 1).encode() + ActionGroupStopped().encode()
              + ActionGroupComplete(2, 1).encode())
    frames, skipped = decode_all(stream, Direction.BOARD)
    assert [f.message for f in frames] == [
        BatteryVoltage(7500), ServoPositions(((1, 1500), (2, 900))), ActionGroupRunning(2, 1),
        ActionGroupStopped(), ActionGroupComplete(2, 1),
    ]
    assert skipped == []


# Hiwonder, "LSC Series Controller Communication Protocol" (public copy:
# github.com/Hiwonder-docs/32-Channel-Servo-Controller, source/docs/2_Communication_Protocol.md)
# section 2.1 examples (host -> board) and section 2.2 (board -> host notices).
VENDOR_COMMANDS = [
    ("55 55 05 06 08 01 00", ActionGroupRun(8, 1)),  # run group 8 once
    ("55 55 05 06 02 00 00", ActionGroupRun(2, 0)),  # run group 2 forever
    ("55 55 02 07", ActionGroupStop()),
    ("55 55 05 0B 08 32 00", ActionGroupSpeed(8, 50)),  # group 8 at 50 %
    ("55 55 05 0B FF 2C 01", ActionGroupSpeed(0xFF, 300)),  # every group at 300 %
    ("55 55 02 0F", GetBatteryVoltage()),
]
VENDOR_NOTICES = [
    ("55 55 05 06 08 01 00", ActionGroupRunning(8, 1)),  # group 8 started, to run once
    ("55 55 02 07", ActionGroupStopped()),  # a running group was stopped
    ("55 55 05 08 08 01 00", ActionGroupComplete(8, 1)),  # group 8 finished its one run
]


@pytest.mark.parametrize(("hex_bytes", "message", "direction"),
                         [(h, m, Direction.HOST) for h, m in VENDOR_COMMANDS]
                         + [(h, m, Direction.BOARD) for h, m in VENDOR_NOTICES])
def test_vendor_sheet_vectors_encode_and_decode_exactly(hex_bytes, message, direction):
    data = bytes.fromhex(hex_bytes)
    assert message.encode() == data
    assert decode_frame(data, direction) == message
    # inside a stream, between the published battery reply / one-servo move
    other = VECTOR_BATTERY if direction is Direction.BOARD else VECTOR_ONE_SERVO
    frames, skipped = decode_all(other + data + other, direction)
    assert [f.raw for f in frames] == [other, data, other] and skipped == []


def test_partial_frame_waits_and_flush_reports_it_truncated():
    decoder = FrameDecoder()
    assert decoder.feed(VECTOR_ONE_SERVO[:7]) == []
    assert decoder.pending == VECTOR_ONE_SERVO[:7]
    assert [f.raw for f in decoder.feed(VECTOR_ONE_SERVO[7:])] == [VECTOR_ONE_SERVO]
    decoder.feed(VECTOR_ONE_SERVO[:5])
    decoder.flush()
    assert [(s.offset, s.data, s.reason) for s in decoder.take_skipped()] == [
        (10, VECTOR_ONE_SERVO[:5], "truncated frame")
    ]
    assert decoder.skipped == [] and decoder.skipped_bytes == 5


# -- false headers: garbage holding 55 55 and plausible bytes before a real frame -------------


POSITIONS_1_1500 = bytes.fromhex("55 55 06 15 01 01 DC 05")  # reply: servo 1 at 1500


@pytest.mark.parametrize(
    ("fake", "real", "message", "why"),
    [pytest.param("55 55 05 06", VECTOR_BATTERY, BatteryVoltage(7500),
                  "not followed by a header", id="group-running-eats-3-bytes"),
     pytest.param("00 55 55 04 0F 12", VECTOR_BATTERY, BatteryVoltage(7500),
                  "not followed by a header", id="battery-eats-1-byte"),
     pytest.param("55 55 05 08 11", VECTOR_BATTERY, BatteryVoltage(7500),
                  "not followed by a header", id="group-complete-eats-2"),
     pytest.param("55 55 0F 15 04 0B 0A 0C 0F", POSITIONS_1_1500, ServoPositions(((1, 1500),)),
                  "ends where this one does", id="positions-eat-all")])
def test_a_false_header_before_a_reply_does_not_swallow_it(fake, real, message, why):
    # each fake start passes every check by taking bytes of the real reply: "55 55 05 06" +
    # "55 55 04" is group 0x55 running 0x0455 times; "55 55 04 0F 12" + "55" a battery reply
    # of 0x5512 mV; "55 55 05 08 11" + "55 55" group 0x11 done 0x5555 times; the last one
    # takes the whole positions reply as its fourth servo (servo 15 at 0x5555 in between)
    fake = bytes.fromhex(fake)
    candidate = fake[fake.index(codec.HEADER):]
    decode_frame((candidate + real)[:candidate[2] + 2], Direction.BOARD)  # valid on its own
    for tail in (b"", ActionGroupStopped().encode()):  # the reply ends the burst, or not
        stream = fake + real + tail
        for cut in range(len(stream) + 1):  # however the reads cut it
            decoder = FrameDecoder(Direction.BOARD)
            frames = decoder.feed(stream[:cut]) + decoder.feed(stream[cut:])
            frames += decoder.idle()  # the line goes quiet after the reply
            assert [(f.offset, f.message) for f in frames] == [(len(fake), message)] + (
                [(len(fake) + len(real), ActionGroupStopped())] if tail else []), (tail, cut)
            skipped = decoder.take_skipped()
            assert [(s.offset, s.data) for s in skipped] == [(0, fake)]
            assert any(why in s.reason for s in [*skipped, *decoder.skipped]) or \
                not skipped[0].reason.startswith("false header"), skipped


def test_a_frame_held_for_the_bytes_after_it_is_decided_by_silence_or_the_next_header():
    # 55 55 05 06 55 55 04 is a complete, valid candidate (group 0x55 running 0x0455 times)
    # with a header inside it: it waits for the bytes that decide
    decoder = FrameDecoder(Direction.BOARD)
    candidate = bytes.fromhex("55 55 05 06 55 55 04")
    assert decoder.feed(candidate) == [] and decoder.pending == candidate
    # ... silence: it was the last thing on the line, so it is a frame
    assert [f.message for f in decoder.idle()] == [ActionGroupRunning(0x55, 0x0455)]
    # followed by a header, it is a frame at once; by the rest of a reply, it is not
    decoder = FrameDecoder(Direction.BOARD)
    assert [f.message for f in decoder.feed(candidate + VECTOR_BATTERY[:2])] == \
        [ActionGroupRunning(0x55, 0x0455)]
    decoder = FrameDecoder(Direction.BOARD)
    assert decoder.feed(candidate + VECTOR_BATTERY[3:]) == []  # is the reply's end the end?
    assert [f.message for f in decoder.idle()] == [BatteryVoltage(7500)]
    decoder = FrameDecoder(Direction.BOARD)
    assert [f.message for f in decoder.feed(candidate + VECTOR_BATTERY[3:] + b"\x55\x55")] \
        == [BatteryVoltage(7500)]
    # a frame with no header inside it never waits, and idle() with nothing held is a no-op
    decoder = FrameDecoder(Direction.BOARD)
    assert [f.raw for f in decoder.feed(VECTOR_BATTERY)] == [VECTOR_BATTERY]
    assert decoder.idle() == [] and decoder.pending == b""


def _decode_in_pieces(stream: bytes, cuts: list[int], direction, end: str
                      ) -> tuple[list, FrameDecoder]:
    """Feed ``stream`` cut at ``cuts`` to a fresh decoder, then end it by ``idle`` (the line
    went quiet) or ``flush`` (end of stream); every frame it gave, and the decoder."""
    decoder = FrameDecoder(direction)
    frames = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        frames += decoder.feed(stream[a:b])
    return frames + getattr(decoder, end)(), decoder


def _no_inner_header(frame: bytes) -> bool:
    """No header starts inside ``frame``: one that did could make it the false one (the
    decoder's documented limit: the bytes cannot tell)."""
    return codec.HEADER not in frame[2:] and not frame.endswith(b"\x55")


@pytest.mark.parametrize("direction", [Direction.HOST, Direction.BOARD])
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_a_false_header_never_swallows_the_frame_after_it(direction, data):
    # garbage: headerless noise, then the start of a valid frame cut short (a fake header with
    # plausible bytes), then a real frame, then silence or the next frame; however the reads
    # cut it, the real frame comes back whole at its offset (the battery query's case)
    messages = host_messages if direction is Direction.HOST else board_messages
    noise = data.draw(headerless_noise)
    whole = data.draw(messages).encode()
    fake = whole[:data.draw(st.integers(2, len(whole) - 1))]
    real = data.draw(messages.map(lambda m: m.encode()).filter(_no_inner_header))
    tail = data.draw(st.one_of(st.just(b""), messages.map(lambda m: m.encode())))
    stream = noise + fake + real + tail
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=4)))
    frames, _ = _decode_in_pieces(stream, cuts, direction, end="idle")
    offset = len(noise) + len(fake)
    assert (offset, real) in [(f.offset, f.raw) for f in frames]


def test_a_lone_trailing_0x55_is_held_back_for_the_next_chunk():
    decoder = FrameDecoder()
    assert decoder.feed(b"\x01\x55") == []
    assert decoder.pending == b"\x55"
    assert [f.raw for f in decoder.feed(VECTOR_ONE_SERVO[1:])] == [VECTOR_ONE_SERVO]


# ---------------------------------------------------------------------------------------------
# property tests

_ids = st.integers(0, codec.SERVO_ID_MAX)
_positions = st.lists(st.tuples(_ids, st.integers(500, 2500)), min_size=1, max_size=33,
                      unique_by=lambda p: p[0])
_id_lists = st.lists(_ids, min_size=1, max_size=33, unique=True)
_u8, _u16 = st.integers(0, 255), st.integers(0, 0xFFFF)

host_messages = st.one_of(
    st.builds(ServoMove, _positions.map(tuple), st.integers(0, 30000)),
    st.builds(ActionGroupRun, _u8, _u16),
    st.just(ActionGroupStop()),
    st.builds(ActionGroupSpeed, _u8, _u16),
    st.just(GetBatteryVoltage()),
    st.builds(MultServoUnload, _id_lists.map(tuple)),
    st.builds(MultServoPosRead, _id_lists.map(tuple)),
)
board_messages = st.one_of(
    st.builds(ActionGroupRunning, _u8, _u16),
    st.just(ActionGroupStopped()),
    st.builds(ActionGroupComplete, _u8, _u16),
    st.builds(BatteryVoltage, _u16),
    st.builds(ServoPositions,
              st.lists(st.tuples(_ids, _u16), min_size=1, max_size=33,
                       unique_by=lambda p: p[0]).map(tuple)),
)
# Garbage in which no header can start: no 55 55, and not ending in 55 (the guarantee).
headerless_noise = st.binary(max_size=12).filter(
    lambda b: b"\x55\x55" not in b and not b.endswith(b"\x55")
)


@pytest.mark.parametrize("direction", [Direction.HOST, Direction.BOARD])
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_random_frames_with_noise_between_all_come_back(direction, data):
    messages = data.draw(st.lists(host_messages if direction is Direction.HOST
                                  else board_messages, max_size=8))
    noises = data.draw(st.lists(headerless_noise, min_size=len(messages) + 1,
                                max_size=len(messages) + 1))
    stream, expected_frames, expected_skips = b"", [], []
    for message, noise in zip(messages, noises, strict=False):
        if noise:
            expected_skips.append((len(stream), noise))
        stream += noise
        expected_frames.append((len(stream), message))
        stream += message.encode()
    if noises[-1]:
        expected_skips.append((len(stream), noises[-1]))
    stream += noises[-1]

    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=5)))
    frames, decoder = _decode_in_pieces(stream, cuts, direction, end="flush")
    assert [(f.offset, f.message) for f in frames] == expected_frames
    assert [(s.offset, s.data) for s in decoder.skipped] == expected_skips


@settings(max_examples=200, deadline=None)
@given(stream=st.binary(max_size=200), cuts=st.lists(st.integers(0, 200), max_size=6),
       direction=st.sampled_from(Direction))
def test_any_bytes_are_accounted_for_whatever_the_chunking(stream, cuts, direction):
    whole, whole_skipped = decode_all(stream, direction)
    decoder = FrameDecoder(direction)
    frames = []
    bounds = sorted(min(c, len(stream)) for c in cuts)
    for a, b in zip([0, *bounds], [*bounds, len(stream)], strict=True):
        frames += decoder.feed(stream[a:b])
    frames += decoder.flush()
    assert frames == whole
    assert decoder.skipped == whole_skipped
    pieces = sorted([(f.offset, f.raw) for f in frames]
                    + [(s.offset, s.data) for s in decoder.skipped])
    assert b"".join(p for _, p in pieces) == stream  # every byte, in order, exactly once
    for f in frames:
        assert decode_frame(f.raw, direction) == f.message


# ---------------------------------------------------------------------------------------------
# the per-frame fast paths: servo_move_arrays and the SERVO_MOVE decoder


def _spec_servo_move(pairs: list[tuple[int, int]], time_ms: int) -> bytes:
    """SERVO_MOVE written straight from the command table of docs/device.md, not by the codec:
    55 55, Length 3n + 5, 0x03, n, time lo hi, n x (id, pos lo, pos hi)."""
    out = [0x55, 0x55, 3 * len(pairs) + 5, 0x03, len(pairs), time_ms & 0xFF, time_ms >> 8]
    for servo, pulse in pairs:
        out += [servo, pulse & 0xFF, pulse >> 8]
    return bytes(out)


def _outcome(make):
    """Bytes (or message), or the DeviceError message: two paths must agree on either."""
    try:
        return make()
    except DeviceError as exc:
        return f"DeviceError: {exc}"


@settings(max_examples=300, deadline=None)
@given(pairs=_positions, time_ms=st.integers(0, 30000),
       dtype=st.sampled_from([np.int64, np.int32, np.uint16, np.intp]))
def test_array_encoder_gives_the_validated_path_bytes_for_valid_frames(pairs, time_ms, dtype):
    ids = np.array([i for i, _ in pairs], dtype=dtype)
    pulses = np.array([p for _, p in pairs], dtype=dtype)
    fast = codec.servo_move_arrays(ids, pulses, time_ms)
    assert fast == codec.servo_move(pairs, time_ms) == _spec_servo_move(pairs, time_ms)
    assert decode_frame(fast) == ServoMove(tuple(pairs), time_ms)


@settings(max_examples=300, deadline=None)
@given(pairs=st.lists(st.tuples(st.integers(-3, 40), st.integers(0, 70000)), max_size=36),
       time_ms=st.integers(-2, 70000))
def test_array_encoder_refuses_exactly_what_the_validated_path_refuses(pairs, time_ms):
    # ids and pulses anywhere (repeats, out of range, none): the same bytes or the same error
    ids = np.array([i for i, _ in pairs], dtype=np.int64)
    pulses = np.array([p for _, p in pairs], dtype=np.int64)
    assert (_outcome(lambda: codec.servo_move_arrays(ids, pulses, time_ms))
            == _outcome(lambda: codec.servo_move(pairs, time_ms)))


@settings(max_examples=300, deadline=None)
@given(triples=st.lists(st.tuples(_u8, _u16), min_size=1, max_size=33), time_ms=_u16)
def test_servo_move_decoder_checks_exactly_as_the_message_does(triples, time_ms):
    # any SERVO_MOVE-shaped bytes: decoded iff ServoMove accepts the values, same error if not
    data = _spec_servo_move(triples, time_ms)
    expected = _outcome(lambda: ServoMove(tuple(triples), time_ms))
    decoded = _outcome(lambda: decode_frame(data))
    if isinstance(expected, str):
        assert decoded == f"DeviceError: LSC frame {data.hex(' ')!r}: " + expected.removeprefix(
            "DeviceError: LSC frame: ")
    else:
        assert decoded == expected
        assert decoded.encode() == data


def test_array_encoder_names_bad_input():
    with pytest.raises(DeviceError, match=r"servo 2 pulse width.*500\.\.2500.*2501"):
        codec.servo_move_arrays(np.array([1, 2]), np.array([1500, 2501]), 100)
    with pytest.raises(DeviceError, match=r"whole number.*1500\.0"):
        codec.servo_move_arrays(np.array([1]), np.array([1500.0]), 100)
    with pytest.raises(DeviceError, match=r"move time.*True"):
        codec.servo_move_arrays(np.array([1]), np.array([1500]), True)
    with pytest.raises(DeviceError, match=r"one pulse width per servo id.*\(2,\).*\(1,\)"):
        codec.servo_move_arrays(np.array([1, 2]), np.array([1500]), 100)
    assert codec.servo_move_arrays(np.array([1]), np.array([2000]), np.int64(1000)) \
        == VECTOR_ONE_SERVO


@settings(max_examples=150, deadline=None)
@given(chunks=st.lists(host_messages.map(lambda m: m.encode())
                       | st.sampled_from([bytes.fromhex("55 55 02 42"),  # unknown command
                                          bytes.fromhex("55 55 05 03 00 00 00"),  # no servos
                                          bytes.fromhex("55 55 08 03 01 E8 03 01 00 00")])
                       | headerless_noise, max_size=8))
def test_whole_frame_chunks_decode_as_the_joined_stream_does(chunks):
    # one chunk = one candidate frame takes the decoder's direct path: same frames, skipped
    # runs, offsets and counts as feeding everything at once
    one = FrameDecoder(Direction.HOST)
    joined = one.feed(b"".join(chunks))
    joined += one.flush()
    each = FrameDecoder(Direction.HOST)
    frames = [f for chunk in chunks for f in each.feed(chunk)]
    frames += each.flush()
    assert frames == joined
    assert each.skipped == one.skipped
    assert (each.position, each.frames_decoded, each.skipped_bytes) == \
        (one.position, one.frames_decoded, one.skipped_bytes)
