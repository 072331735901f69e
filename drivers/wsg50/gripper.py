"""WSG 50 gripper over a serial line (pyserial) or TCP, behind the ``Gripper`` interface.

One reader task decodes the byte stream and dispatches frames by command id: to the request
waiting for that id, and, for width, force and system state, to a cache that the gripper's
automatic updates keep fresh (they double as a heartbeat: a stale cache is a device timeout).
Motion commands answer CMD_PENDING first; the request then waits for the final reply. A move
sets the gripper's force limit and pre-positions with stop-on-block, so contact ends it with
AXIS_BLOCKED, which ``move`` returns as ``blocked=True``. Nothing here blocks the event loop:
the serial port is opened in a thread and read and written through its non-blocking fd.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import math
import os
import struct
import time
from collections import defaultdict
from typing import Any

import serial

from drivers.base import (
    DeviceConnectionError,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Gripper,
    GripperState,
    MotionRejectedError,
)
from drivers.config import GripperConfig
from drivers.latest_frame import open_in_thread
from drivers.wsg50.protocol import (
    ACK_FAST_STOP_PAYLOAD,
    Command,
    Frame,
    FrameDecoder,
    PrePositionFlag,
    Reply,
    Status,
    SystemFlag,
    UpdateFlag,
    WSGProtocolError,
    encode_frame,
    homing_payload,
    pre_position_payload,
    status_error,
    update_payload,
)

log = logging.getLogger(__name__)

AUTO_UPDATED = (Command.GET_SYSTEM_STATE, Command.GET_WIDTH, Command.GET_FORCE)
"""Values the gripper streams to the driver once connected."""
LOOP_PROBE = b"touchshape"
"""Echoed by the LOOP command on connect: proves the link both ways before anything moves."""


# --- transports -----------------------------------------------------------------------------------


class WSGTransport(abc.ABC):
    """A byte pipe to the gripper. ``write`` never blocks; ``read`` returns available bytes."""

    description: str

    @abc.abstractmethod
    async def open(self, timeout_s: float) -> None: ...

    @abc.abstractmethod
    async def read(self) -> bytes:
        """At least one byte; DeviceConnectionError when the link is gone."""

    @abc.abstractmethod
    def write(self, data: bytes) -> None: ...

    @abc.abstractmethod
    async def close(self) -> None:
        """Flush briefly and release; safe to call twice."""


class SerialTransport(WSGTransport):
    """pyserial port (a USB adapter, or a pty in tests) read and written without blocking."""

    def __init__(self, port: str, baudrate: int) -> None:
        self.port = port
        self.baudrate = baudrate
        self.description = f"serial {port} at {baudrate} baud"
        self._serial: Any = None
        self._pending = bytearray()

    async def open(self, timeout_s: float) -> None:
        def open_port() -> Any:
            # timeout=0: reads return what is there; the loop waits for readiness instead.
            return serial.Serial(self.port, self.baudrate, timeout=0, write_timeout=0)

        try:
            self._serial = await open_in_thread(
                open_port, timeout_s, what=f"opening {self.description}", close_late=_close_quietly
            )
        except (serial.SerialException, OSError, ValueError) as error:
            raise DeviceConnectionError(f"cannot open {self.description}: {error}") from error
        os.set_blocking(self._serial.fileno(), False)

    async def read(self) -> bytes:
        port = self._require_open()
        loop = asyncio.get_running_loop()
        while True:
            try:
                data: bytes = port.read(max(1, port.in_waiting))
            except (serial.SerialException, OSError) as error:
                raise DeviceConnectionError(f"{self.description}: {error}") from error
            if data:
                return data
            readable = loop.create_future()
            loop.add_reader(port.fileno(), _set_once, readable)
            try:
                await readable
            finally:
                loop.remove_reader(port.fileno())

    def write(self, data: bytes) -> None:
        port = self._require_open()
        self._pending += data
        self._flush(port.fileno())

    def _flush(self, fd: int) -> None:
        loop = asyncio.get_running_loop()
        try:
            written = os.write(fd, self._pending)
        except BlockingIOError:
            written = 0
        except OSError as error:
            raise DeviceConnectionError(f"{self.description}: {error}") from error
        del self._pending[:written]
        loop.remove_writer(fd)
        if self._pending:
            # The line is slower than we write: finish when the fd is writable again.
            loop.add_writer(fd, self._flush_when_writable, fd)

    def _flush_when_writable(self, fd: int) -> None:
        try:
            self._flush(fd)
        except DeviceConnectionError as error:
            # A loop callback has no caller to raise to; the reader reports the dead line.
            log.error("%s: write failed: %s", self.description, error)

    async def close(self) -> None:
        if self._serial is None:
            return
        port, self._serial = self._serial, None
        with contextlib.suppress(RuntimeError):
            asyncio.get_running_loop().remove_writer(port.fileno())
        self._pending.clear()
        _close_quietly(port)

    def _require_open(self) -> Any:
        if self._serial is None:
            raise DeviceConnectionError(f"{self.description} is closed")
        return self._serial


class TcpTransport(WSGTransport):
    """The WSG 50's TCP command interface (default 192.168.1.20:1000) via asyncio streams."""

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = port
        self.description = f"tcp {host}:{port}"
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def open(self, timeout_s: float) -> None:
        try:
            async with asyncio.timeout(timeout_s):
                self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        except TimeoutError:
            raise DeviceTimeoutError(
                f"connecting to {self.description} took over {timeout_s} s"
            ) from None
        except OSError as error:
            raise DeviceConnectionError(f"cannot connect to {self.description}: {error}") from error

    async def read(self) -> bytes:
        if self._reader is None:
            raise DeviceConnectionError(f"{self.description} is closed")
        try:
            data = await self._reader.read(4096)
        except OSError as error:
            raise DeviceConnectionError(f"{self.description}: {error}") from error
        if not data:
            raise DeviceConnectionError(f"{self.description}: the gripper closed the connection")
        return data

    def write(self, data: bytes) -> None:
        if self._writer is None:
            raise DeviceConnectionError(f"{self.description} is closed")
        self._writer.write(data)  # buffered by the transport, never blocks

    async def close(self) -> None:
        if self._writer is None:
            return
        writer, self._writer, self._reader = self._writer, None, None
        writer.close()
        with contextlib.suppress(OSError, TimeoutError):
            async with asyncio.timeout(0.5):
                await writer.wait_closed()


def transport_for(config: GripperConfig) -> WSGTransport:
    if config.type == "wsg50_serial":
        return SerialTransport(config.serial_port, config.baudrate)
    if config.type == "wsg50_tcp":
        return TcpTransport(config.host, config.tcp_port)
    raise ValueError(f"gripper type {config.type!r} is not a WSG 50 link")


# --- driver ---------------------------------------------------------------------------------------


def check_move_limits(
    width_m: float, speed_m_s: float, force_limit_n: float, config: GripperConfig
) -> None:
    """MotionRejectedError unless width is in the stroke and speed and force are in (0, max]."""
    if not (math.isfinite(width_m) and 0.0 <= width_m <= config.stroke_m):
        raise MotionRejectedError(f"width {width_m} m outside the stroke 0..{config.stroke_m} m")
    if not 0.0 < speed_m_s <= config.max_speed_m_s:
        raise MotionRejectedError(
            f"speed {speed_m_s} m/s outside (0, max_speed_m_s = {config.max_speed_m_s}]"
        )
    if not 0.0 < force_limit_n <= config.max_force_n:
        raise MotionRejectedError(
            f"force limit {force_limit_n} N outside (0, max_force_n = {config.max_force_n}]"
        )


class WSG50Gripper(Gripper):
    """The real WSG 50 (or the emulator in ``drivers.sim.wsg50_emulator``)."""

    def __init__(self, config: GripperConfig, transport: WSGTransport | None = None) -> None:
        self.config = config
        self.transport = transport if transport is not None else transport_for(config)
        self._decoder = FrameDecoder()
        self._reader_task: asyncio.Task[None] | None = None
        self._connected = False
        self._link_error: DeviceError | None = None
        self._waiters: dict[int, asyncio.Queue[Reply | DeviceError]] = {}
        self._locks: defaultdict[int, asyncio.Lock] = defaultdict(asyncio.Lock)
        self._updated = asyncio.Condition()
        self._values: dict[int, Reply] = {}
        self._updated_at: dict[int, float] = {}
        self._force_limit_n: float | None = None

    # --- lifecycle ------------------------------------------------------------------------------

    async def connect(self) -> None:
        """Open the link, check it with a loop echo, start the automatic state updates."""
        if self._connected:
            return
        try:
            await self.transport.open(self.config.connect_timeout_s)
            self._link_error = None
            self._reader_task = asyncio.create_task(self._read_loop(), name="wsg50-reader")
            self._connected = True
            echo = await self._request(Command.LOOP, LOOP_PROBE)
            if echo.params != LOOP_PROBE:
                raise WSGProtocolError(f"loop echo was {echo.params!r}, sent {LOOP_PROBE!r}")
            period = update_payload(UpdateFlag.AUTO, self.config.state_update_period_ms)
            for command in AUTO_UPDATED:
                await self.command(command, period)
            limit = await self.command(Command.GET_FORCE_LIMIT)
            self._force_limit_n = limit.float_value()
        except BaseException:
            await self.close()
            raise
        log.info("WSG 50 connected over %s", self.transport.description)

    async def close(self) -> None:
        """Stop the automatic updates, announce the disconnect, close the link. Does not wait
        for replies, so closing a silent or broken link is quick."""
        if self._connected and self._link_error is None:
            with contextlib.suppress(DeviceError):
                for command in AUTO_UPDATED:
                    self.transport.write(encode_frame(command, update_payload(UpdateFlag(0), 0)))
                self.transport.write(encode_frame(Command.DISCONNECT))
        self._connected = False
        if self._reader_task is not None:
            self._reader_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader_task
            self._reader_task = None
        await self.transport.close()
        self._values.clear()
        self._updated_at.clear()

    @property
    def is_connected(self) -> bool:
        return self._connected and self._link_error is None

    # --- commands -------------------------------------------------------------------------------

    async def home(self, *, timeout_s: float = 10.0) -> None:
        """Reference the fingers in the direction configured on the gripper."""
        await self.command(Command.HOMING, homing_payload(0), final_timeout_s=timeout_s)
        # So that state() right after homing shows the homed fingers, not the last update.
        await self._fresh_state(time.monotonic(), timeout_s=self.config.timeout_s)

    async def move(
        self, width_m: float, *, speed_m_s: float, force_limit_n: float, timeout_s: float
    ) -> GripperState:
        """Pre-position to ``width_m`` with stop-on-block under the gripper's force limit.

        Returns ``blocked=True`` when the fingers stopped on contact; a stop() during the move
        ends it with ``blocked=False`` short of the width. Timeout and cancellation stop the
        fingers before the error propagates.
        """
        check_move_limits(width_m, speed_m_s, force_limit_n, self.config)
        if self._force_limit_n is None or not math.isclose(self._force_limit_n, force_limit_n):
            await self.command(Command.SET_FORCE_LIMIT, struct.pack("<f", force_limit_n))
            self._force_limit_n = force_limit_n
        payload = pre_position_payload(
            width_m * 1e3, speed_m_s * 1e3, PrePositionFlag.STOP_ON_BLOCK
        )
        reply = await self._request(Command.PRE_POSITION, payload, final_timeout_s=timeout_s)
        if reply.status not in (Status.SUCCESS, Status.AXIS_BLOCKED, Status.CMD_ABORTED):
            raise status_error(reply.command, reply.status)
        since = time.monotonic()
        state = await self._fresh_state(since, timeout_s=self.config.timeout_s)
        return GripperState(
            width_m=state.width_m,
            force_n=state.force_n,
            is_moving=state.is_moving,
            blocked=reply.status == Status.AXIS_BLOCKED,
            timestamp_s=state.timestamp_s,
        )

    async def stop(self) -> None:
        """Stop the fingers; a running move returns with what it reached."""
        await self.command(Command.STOP)

    async def fast_stop(self) -> None:
        """Emergency stop: the gripper refuses motion until ``acknowledge_fast_stop``."""
        await self.command(Command.FAST_STOP)

    async def acknowledge_fast_stop(self) -> None:
        await self.command(Command.ACK_FAST_STOP, ACK_FAST_STOP_PAYLOAD)

    async def command(
        self, command: int, payload: bytes = b"", *, final_timeout_s: float | None = None
    ) -> Reply:
        """Send any command and return its successful reply (diagnostics, and commands without
        a method here); pass ``final_timeout_s`` for motion commands. An error status raises
        its typed exception (``drivers.wsg50.protocol.status_error``)."""
        reply = await self._request(command, payload, final_timeout_s=final_timeout_s)
        return self._expect_success(reply)

    async def state(self) -> GripperState:
        """The latest automatic update; DeviceTimeoutError if it is older than
        ``max_state_age_s`` (the gripper went silent)."""
        self._require_connected()
        if len(self._updated_at) < len(AUTO_UPDATED):
            raise DeviceTimeoutError("no state update from the WSG 50 yet")
        age_s = time.monotonic() - min(self._updated_at.values())
        if age_s > self.config.max_state_age_s:
            raise DeviceTimeoutError(
                f"no state update from the WSG 50 for {age_s:.2f} s"
                f" (max_state_age_s = {self.config.max_state_age_s})"
            )
        flags = self.system_flags
        return GripperState(
            width_m=self._values[Command.GET_WIDTH].float_value() * 1e-3,
            force_n=self._values[Command.GET_FORCE].float_value(),
            is_moving=SystemFlag.MOVING in flags,
            blocked=bool(flags & (SystemFlag.BLOCKED_MINUS | SystemFlag.BLOCKED_PLUS)),
            timestamp_s=max(self._updated_at.values()),
        )

    @property
    def system_flags(self) -> SystemFlag:
        """The latest system state bits (referenced, moving, blocked, fast stop, faults)."""
        reply = self._values.get(Command.GET_SYSTEM_STATE)
        return reply.system_flags() if reply is not None else SystemFlag(0)

    @property
    def force_limit_n(self) -> float | None:
        return self._force_limit_n

    # --- frames ---------------------------------------------------------------------------------

    async def _request(
        self, command: int, payload: bytes = b"", *, final_timeout_s: float | None = None
    ) -> Reply:
        """Send one command and return its reply; for motion commands (``final_timeout_s``
        given) the final reply after CMD_PENDING. One outstanding request per command id."""
        self._require_connected()
        async with self._locks[command]:
            queue: asyncio.Queue[Reply | DeviceError] = asyncio.Queue()
            self._waiters[command] = queue
            try:
                self.transport.write(encode_frame(command, payload))
                try:
                    reply = await self._next_reply(queue, command, self.config.timeout_s)
                    if reply.status == Status.CMD_PENDING:
                        if final_timeout_s is None:
                            raise WSGProtocolError(f"unexpected CMD_PENDING for 0x{command:02X}")
                        reply = await self._next_reply(queue, command, final_timeout_s)
                except (asyncio.CancelledError, DeviceTimeoutError):
                    if final_timeout_s is not None:  # a motion may be under way
                        await asyncio.shield(self._abort_motion(queue, command))
                    raise
            finally:
                del self._waiters[command]
        return reply

    async def _abort_motion(self, queue: asyncio.Queue[Reply | DeviceError], command: int) -> None:
        """Stop the fingers after a motion timed out or was cancelled, and take the motion's
        final (aborted) reply off the line, so that it cannot be mistaken for the reply to
        the next command with this id. Best effort, bounded by ``timeout_s``."""
        with contextlib.suppress(DeviceError, TimeoutError):
            async with asyncio.timeout(self.config.timeout_s):
                await self.command(Command.STOP)
                # Aborted before its pending reply was read, the final one still follows.
                while True:
                    item = await queue.get()
                    if isinstance(item, DeviceError) or item.status != Status.CMD_PENDING:
                        break

    async def _next_reply(
        self, queue: asyncio.Queue[Reply | DeviceError], command: int, timeout_s: float
    ) -> Reply:
        try:
            async with asyncio.timeout(timeout_s):
                item = await queue.get()
        except TimeoutError:
            bad = self._decoder.crc_errors
            note = f"; {bad} frames with a bad CRC dropped so far" if bad else ""
            raise DeviceTimeoutError(
                f"WSG 50 did not answer 0x{command:02X} within {timeout_s} s"
                f" over {self.transport.description}{note}"
            ) from None
        if isinstance(item, DeviceError):
            raise item
        return item

    @staticmethod
    def _expect_success(reply: Reply) -> Reply:
        if reply.status != Status.SUCCESS:
            raise status_error(reply.command, reply.status)
        return reply

    async def _read_loop(self) -> None:
        try:
            while True:
                data = await self.transport.read()
                for frame in self._decoder.feed(data):
                    await self._dispatch(frame)
        except DeviceError as error:
            log.error("WSG 50 link lost: %s", error)
            self._link_error = error
            for queue in self._waiters.values():
                queue.put_nowait(error)

    async def _dispatch(self, frame: Frame) -> None:
        try:
            reply = Reply.from_frame(frame)
        except WSGProtocolError as error:
            log.warning("dropped a WSG 50 frame: %s", error)
            return
        queue = self._waiters.get(frame.command)
        if queue is not None:
            queue.put_nowait(reply)
        if frame.command in AUTO_UPDATED and reply.status == Status.SUCCESS:
            if len(reply.params) != 4:
                log.warning(
                    "dropped a WSG 50 update 0x%02X of %d bytes", frame.command, len(reply.params)
                )
                return
            self._values[frame.command] = reply
            self._updated_at[frame.command] = time.monotonic()
            async with self._updated:
                self._updated.notify_all()
        elif queue is None:
            log.debug("unsolicited WSG 50 frame 0x%02X status %d", frame.command, reply.status)

    async def _fresh_state(self, since: float, *, timeout_s: float) -> GripperState:
        """The state once every automatic update has arrived after ``since`` (monotonic s)."""
        try:
            async with asyncio.timeout(timeout_s), self._updated:
                await self._updated.wait_for(
                    lambda: (
                        len(self._updated_at) == len(AUTO_UPDATED)
                        and min(self._updated_at.values()) > since
                    )
                )
        except TimeoutError:
            raise DeviceTimeoutError(
                f"no state update from the WSG 50 within {timeout_s} s after the move"
            ) from None
        return await self.state()

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceNotConnectedError("WSG 50 is not connected")
        if self._link_error is not None:
            raise DeviceConnectionError(f"WSG 50 link lost: {self._link_error}")


# --- helpers --------------------------------------------------------------------------------------


def _set_once(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


def _close_quietly(port: Any) -> None:
    with contextlib.suppress(Exception):
        port.close()
