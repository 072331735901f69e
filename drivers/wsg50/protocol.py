"""WSG 50 binary protocol: framing, CRC, command ids, status codes and their typed errors.

A frame is ``AA AA AA | id u8 | length u16 LE | payload | CRC16 u16 LE``; the CRC runs over the
whole frame including the preamble. Replies start with a u16 status; a motion command first
answers ``CMD_PENDING`` (26) and later sends a final reply with the same id. Values are
little-endian: floats are f32 in millimetres, mm/s, mm/s^2 and newtons. Pure functions and a
byte-stream decoder only; the transport and the driver are in ``drivers.wsg50.gripper``.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from drivers.base import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeoutError,
    MotionRejectedError,
)

PREAMBLE = b"\xaa\xaa\xaa"
HEADER_SIZE = len(PREAMBLE) + 3
CRC_SIZE = 2
MAX_PAYLOAD_SIZE = 1024
"""Larger than any WSG 50 frame; a longer length field means the decoder is out of step."""


class Command(enum.IntEnum):
    LOOP = 0x06
    DISCONNECT = 0x07
    HOMING = 0x20
    PRE_POSITION = 0x21
    STOP = 0x22
    FAST_STOP = 0x23
    ACK_FAST_STOP = 0x24
    GRASP = 0x25
    RELEASE = 0x26
    SET_ACCELERATION = 0x30
    GET_ACCELERATION = 0x31
    SET_FORCE_LIMIT = 0x32
    GET_FORCE_LIMIT = 0x33
    TARE_FORCE = 0x38
    GET_SYSTEM_STATE = 0x40
    GET_GRASP_STATE = 0x41
    GET_WIDTH = 0x43
    GET_SPEED = 0x44
    GET_FORCE = 0x45


MOTION_COMMANDS = frozenset({Command.HOMING, Command.PRE_POSITION, Command.GRASP, Command.RELEASE})
"""Commands that answer CMD_PENDING first and their outcome in a second reply."""

ACK_FAST_STOP_PAYLOAD = b"ack"
"""The fast-stop acknowledgement must carry these three bytes."""


class Status(enum.IntEnum):
    SUCCESS = 0
    NOT_AVAILABLE = 1
    NO_SENSOR = 2
    NOT_INITIALIZED = 3
    ALREADY_RUNNING = 4
    FEATURE_NOT_SUPPORTED = 5
    INCONSISTENT_DATA = 6
    TIMEOUT = 7
    READ_ERROR = 8
    WRITE_ERROR = 9
    INSUFFICIENT_RESOURCES = 10
    CHECKSUM_ERROR = 11
    NO_PARAM_EXPECTED = 12
    NOT_ENOUGH_PARAMS = 13
    CMD_UNKNOWN = 14
    CMD_FORMAT_ERROR = 15
    ACCESS_DENIED = 16
    ALREADY_OPEN = 17
    CMD_FAILED = 18
    CMD_ABORTED = 19
    INVALID_HANDLE = 20
    NOT_FOUND = 21
    NOT_OPEN = 22
    IO_ERROR = 23
    INVALID_PARAMETER = 24
    INDEX_OUT_OF_BOUNDS = 25
    CMD_PENDING = 26
    OVERRUN = 27
    RANGE_ERROR = 28
    AXIS_BLOCKED = 29
    FILE_EXISTS = 30


class SystemFlag(enum.IntFlag):
    """Bits of the u32 system state (command 0x40)."""

    REFERENCED = 1 << 0
    MOVING = 1 << 1
    BLOCKED_MINUS = 1 << 2
    BLOCKED_PLUS = 1 << 3
    SOFT_LIMIT_MINUS = 1 << 4
    SOFT_LIMIT_PLUS = 1 << 5
    AXIS_STOPPED = 1 << 6
    TARGET_POS_REACHED = 1 << 7
    FORCE_CONTROL_MODE = 1 << 9
    FAST_STOP = 1 << 12
    TEMP_WARNING = 1 << 13
    TEMP_FAULT = 1 << 14
    POWER_FAULT = 1 << 15
    CURRENT_FAULT = 1 << 16
    FINGER_FAULT = 1 << 17
    CMD_FAILURE = 1 << 18
    SCRIPT_RUNNING = 1 << 19
    SCRIPT_FAILURE = 1 << 20


def describe_flags(flags: SystemFlag) -> str:
    """The set bits by name ("REFERENCED, TARGET_POS_REACHED"), or "none"."""
    return ", ".join(flag.name or "" for flag in SystemFlag if flag in flags) or "none"


FAULT_FLAGS = (
    SystemFlag.FAST_STOP
    | SystemFlag.TEMP_FAULT
    | SystemFlag.POWER_FAULT
    | SystemFlag.CURRENT_FAULT
    | SystemFlag.FINGER_FAULT
)


class PrePositionFlag(enum.IntFlag):
    RELATIVE = 1 << 0
    """Width is relative to the current opening (absolute when clear)."""
    STOP_ON_BLOCK = 1 << 1
    """Stop and answer AXIS_BLOCKED on contact instead of clamping at the force limit."""


class UpdateFlag(enum.IntFlag):
    """First payload byte of the value queries 0x40..0x45; a u16 period in ms follows."""

    AUTO = 1 << 0
    """Send the value periodically until disabled."""
    ON_CHANGE = 1 << 1
    """With AUTO: send only when the value changed."""


# --- CRC ------------------------------------------------------------------------------------------


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """The WSG's CRC16: table of polynomial 0x1021, init 0xFFFF, LSB-first update."""
    for byte in data:
        crc = _CRC_TABLE[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc


# --- frames ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Frame:
    command: int
    payload: bytes
    crc_ok: bool = True


def encode_frame(command: int, payload: bytes = b"") -> bytes:
    """One complete frame with preamble and CRC."""
    if len(payload) > MAX_PAYLOAD_SIZE:
        raise ValueError(f"payload of {len(payload)} bytes is over {MAX_PAYLOAD_SIZE}")
    head = PREAMBLE + struct.pack("<BH", command, len(payload)) + payload
    return head + struct.pack("<H", crc16(head))


class FrameDecoder:
    """Turns a byte stream into frames: keeps partial frames across ``feed`` calls and resyncs
    on the next preamble after garbage or a bad CRC (counted in ``crc_errors``). With
    ``report_bad`` a frame with a bad CRC is also returned, marked ``crc_ok=False`` (a device
    answers it with CHECKSUM_ERROR)."""

    def __init__(self, *, report_bad: bool = False) -> None:
        self.report_bad = report_bad
        self._buffer = bytearray()
        self.crc_errors = 0
        self.discarded_bytes = 0

    def feed(self, data: bytes) -> list[Frame]:
        self._buffer += data
        frames = []
        while True:
            start = self._buffer.find(PREAMBLE)
            if start < 0:
                # Keep a trailing AA or AA AA: it may be the start of the next preamble.
                keep = len(self._buffer) - len(self._buffer.rstrip(b"\xaa"))
                keep = min(keep, len(PREAMBLE) - 1)
                self._discard(len(self._buffer) - keep)
                return frames
            self._discard(start)
            if len(self._buffer) < HEADER_SIZE:
                return frames
            command, length = struct.unpack_from("<BH", self._buffer, len(PREAMBLE))
            if length > MAX_PAYLOAD_SIZE:
                self._discard(1)
                continue
            size = HEADER_SIZE + length + CRC_SIZE
            if len(self._buffer) < size:
                return frames
            (crc,) = struct.unpack_from("<H", self._buffer, size - CRC_SIZE)
            if crc16(bytes(self._buffer[: size - CRC_SIZE])) != crc:
                # Not a frame after all (or a corrupted one): look for the next preamble
                # from the byte after this one's start.
                self.crc_errors += 1
                if self.report_bad:
                    frames.append(Frame(command, b"", crc_ok=False))
                self._discard(1)
                continue
            frames.append(Frame(command, bytes(self._buffer[HEADER_SIZE : size - CRC_SIZE])))
            del self._buffer[:size]

    def _discard(self, count: int) -> None:
        self.discarded_bytes += count
        del self._buffer[:count]


# --- replies and payloads -------------------------------------------------------------------------


@dataclass(frozen=True)
class Reply:
    command: int
    status: int
    params: bytes

    @classmethod
    def from_frame(cls, frame: Frame) -> Reply:
        if len(frame.payload) < 2:
            raise WSGProtocolError(
                f"reply to 0x{frame.command:02X} has {len(frame.payload)} bytes, no status"
            )
        (status,) = struct.unpack_from("<H", frame.payload)
        return cls(frame.command, status, frame.payload[2:])

    def float_value(self) -> float:
        """The f32 that value queries (width, speed, force, limits) return."""
        if len(self.params) != 4:
            raise WSGProtocolError(
                f"reply to 0x{self.command:02X} has {len(self.params)} value bytes, expected 4"
            )
        return float(struct.unpack("<f", self.params)[0])

    def system_flags(self) -> SystemFlag:
        if len(self.params) != 4:
            raise WSGProtocolError(f"system state reply has {len(self.params)} bytes, expected 4")
        return SystemFlag(struct.unpack("<I", self.params)[0])


def encode_reply(command: int, status: int, params: bytes = b"") -> bytes:
    return encode_frame(command, struct.pack("<H", status) + params)


def homing_payload(direction: int = 0) -> bytes:
    """0: the direction configured on the gripper, 1: opening, 2: closing."""
    return struct.pack("<B", direction)


def pre_position_payload(width_mm: float, speed_mm_s: float, flags: PrePositionFlag) -> bytes:
    return struct.pack("<Bff", flags, width_mm, speed_mm_s)


def update_payload(flags: UpdateFlag, period_ms: int) -> bytes:
    """Payload of the value queries: one-shot (flags 0) or automatic every ``period_ms``."""
    return struct.pack("<BH", flags, period_ms)


# --- errors ---------------------------------------------------------------------------------------


def _name(kind: type[enum.IntEnum], value: int) -> str:
    try:
        return kind(value).name
    except ValueError:
        return "UNKNOWN"


class WSGProtocolError(DeviceConnectionError):
    """A frame that decodes but does not make sense (wrong size, missing status)."""


class WSGStatusError(DeviceError):
    """The gripper answered a command with an error status."""

    def __init__(self, command: int, status: int, message: str = "") -> None:
        self.command = command
        self.status = status
        text = (
            f"WSG 50 {_name(Command, command)} (0x{command:02X}) failed:"
            f" {_name(Status, status)} ({status})"
        )
        super().__init__(f"{text}: {message}" if message else text)


class WSGRejectedError(WSGStatusError, MotionRejectedError):
    """The gripper refused the command (bad or out-of-range parameter, not referenced, busy,
    in fast stop)."""


class WSGAxisBlockedError(WSGStatusError, MotionRejectedError):
    """The fingers were blocked (where blocking is a failure, e.g. while homing)."""


class WSGAbortedError(WSGStatusError):
    """A stop or fast stop aborted the command."""


class WSGDeviceTimeoutError(WSGStatusError, DeviceTimeoutError):
    """The gripper itself reported a timeout."""


class WSGChecksumError(WSGStatusError, DeviceConnectionError):
    """The gripper received our frame with a bad CRC: the line is corrupting data."""


_REJECTED = {
    Status.NOT_INITIALIZED,
    Status.ALREADY_RUNNING,
    Status.FEATURE_NOT_SUPPORTED,
    Status.NO_PARAM_EXPECTED,
    Status.NOT_ENOUGH_PARAMS,
    Status.CMD_UNKNOWN,
    Status.CMD_FORMAT_ERROR,
    Status.ACCESS_DENIED,
    Status.INVALID_PARAMETER,
    Status.INDEX_OUT_OF_BOUNDS,
    Status.RANGE_ERROR,
}


def status_error(command: int, status: int, message: str = "") -> WSGStatusError:
    """The typed exception for an error status."""
    if status in _REJECTED:
        return WSGRejectedError(command, status, message)
    cls = {
        Status.AXIS_BLOCKED: WSGAxisBlockedError,
        Status.CMD_ABORTED: WSGAbortedError,
        Status.TIMEOUT: WSGDeviceTimeoutError,
        Status.CHECKSUM_ERROR: WSGChecksumError,
    }.get(status, WSGStatusError)
    return cls(command, status, message)
