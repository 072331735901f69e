"""WSG 50 framing, CRC, decoder and status codes, byte for byte."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.base import DeviceConnectionError, DeviceTimeoutError, MotionRejectedError
from drivers.wsg50.protocol import (
    Command,
    Frame,
    FrameDecoder,
    PrePositionFlag,
    Reply,
    Status,
    UpdateFlag,
    WSGAbortedError,
    WSGAxisBlockedError,
    WSGChecksumError,
    WSGDeviceTimeoutError,
    WSGProtocolError,
    WSGRejectedError,
    crc16,
    encode_frame,
    encode_reply,
    homing_payload,
    pre_position_payload,
    status_error,
    update_payload,
)

HOMING = bytes.fromhex("aa aa aa 20 01 00 00 8f 83")
"""The homing frame as the WSG 50 documentation prints it."""


def test_homing_frame_matches_the_documented_bytes() -> None:
    assert encode_frame(Command.HOMING, homing_payload(0)) == HOMING
    assert crc16(HOMING[:-2]) == 0x838F


def test_pre_position_and_force_frames() -> None:
    payload = pre_position_payload(60.0, 50.0, PrePositionFlag.STOP_ON_BLOCK)
    assert encode_frame(Command.PRE_POSITION, payload) == bytes.fromhex(
        "aa aa aa 21 09 00 02 00 00 70 42 00 00 48 42 72 db"
    )
    assert encode_frame(Command.GET_FORCE, update_payload(UpdateFlag.AUTO, 20)) == bytes.fromhex(
        "aa aa aa 45 03 00 01 14 00 99 7e"
    )
    # A force reply of 5.0 N: status 0, then the f32.
    force = bytes.fromhex("aa aa aa 45 06 00 00 00 00 00 a0 40 63 c9")
    assert encode_reply(Command.GET_FORCE, Status.SUCCESS, struct.pack("<f", 5.0)) == force
    (frame,) = FrameDecoder().feed(force)
    reply = Reply.from_frame(frame)
    assert (reply.command, reply.status, reply.float_value()) == (0x45, 0, 5.0)


def test_crc_of_a_frame_including_its_crc_is_zero() -> None:
    # The property of this CRC that devices use to check a whole frame at once.
    rng = np.random.default_rng(7)
    for _ in range(20):
        payload = rng.integers(0, 256, int(rng.integers(0, 40))).astype(np.uint8).tobytes()
        assert crc16(encode_frame(int(rng.integers(0, 256)), payload)) == 0


def test_decoder_reassembles_frames_split_at_every_byte() -> None:
    stream = HOMING + encode_reply(0x20, Status.CMD_PENDING) + encode_frame(0x06, b"\xaa" * 5)
    decoder = FrameDecoder()
    frames = [frame for byte in stream for frame in decoder.feed(bytes([byte]))]
    assert frames == [
        Frame(0x20, b"\x00"),
        Frame(0x20, b"\x1a\x00"),
        Frame(0x06, b"\xaa" * 5),
    ]
    assert decoder.discarded_bytes == 0


def test_decoder_skips_garbage_and_resyncs_after_a_bad_crc() -> None:
    bad = bytearray(encode_reply(0x43, Status.SUCCESS, struct.pack("<f", 12.5)))
    bad[-1] ^= 0x01
    good = encode_reply(0x45, Status.SUCCESS, struct.pack("<f", 1.0))
    decoder = FrameDecoder()
    frames = decoder.feed(b"\x00\xaa\x13" + bytes(bad) + b"\xaa\xaa" + good)
    assert frames == [Frame(0x45, good[6:-2])]
    assert decoder.crc_errors == 1


def test_decoder_reports_bad_frames_when_asked() -> None:
    bad = bytearray(HOMING)
    bad[6] = 0x01
    frames = FrameDecoder(report_bad=True).feed(bytes(bad) + HOMING)
    assert [(f.command, f.crc_ok) for f in frames] == [(0x20, False), (0x20, True)]


def test_decoder_does_not_wait_forever_on_an_absurd_length() -> None:
    frames = FrameDecoder().feed(b"\xaa\xaa\xaa\x20\xff\xff" + HOMING)
    assert frames == [Frame(0x20, b"\x00")]


def test_reply_without_status_is_a_protocol_error() -> None:
    with pytest.raises(WSGProtocolError):
        Reply.from_frame(Frame(0x43, b"\x00"))
    with pytest.raises(WSGProtocolError):
        Reply(0x43, 0, b"\x00\x00").float_value()


@pytest.mark.parametrize(
    ("status", "error_type", "base"),
    [
        (Status.AXIS_BLOCKED, WSGAxisBlockedError, MotionRejectedError),
        (Status.CMD_UNKNOWN, WSGRejectedError, MotionRejectedError),
        (Status.RANGE_ERROR, WSGRejectedError, MotionRejectedError),
        (Status.ACCESS_DENIED, WSGRejectedError, MotionRejectedError),
        (Status.TIMEOUT, WSGDeviceTimeoutError, DeviceTimeoutError),
        (Status.CHECKSUM_ERROR, WSGChecksumError, DeviceConnectionError),
        (Status.CMD_ABORTED, WSGAbortedError, WSGAbortedError),
    ],
)
def test_status_codes_map_to_typed_errors(status, error_type, base) -> None:
    error = status_error(Command.PRE_POSITION, status)
    assert type(error) is error_type and isinstance(error, base)
    assert error.status == status and error.command == 0x21
    assert f"({int(status)})" in str(error) and "PRE_POSITION" in str(error)


def test_unknown_status_still_names_its_number() -> None:
    error = status_error(0x7F, 99)
    assert "UNKNOWN" in str(error) and "99" in str(error)
