"""A WSG 50 that speaks the real binary protocol on a pseudo-terminal or a TCP socket.

It is backed by the simulated gripper (``SimWSG50``) on a ``SimWorld``, so opening the fingers
toward an object makes the gel force rise and the axis block (status 29) as on the robot. It
serves the commands the driver uses, with their pending and final replies, status codes, the
automatic value updates and the fast stop; grasp and release (0x25, 0x26) are not emulated and
answer FEATURE_NOT_SUPPORTED. Faults for tests: ``silent`` (the device stops answering),
``corrupt_next_reply_to`` (the next frame for these command ids goes out with a bad CRC) and
``chunk_size`` (frames split into and joined across small writes, as a serial line delivers
them).

``touchshape sim wsg --pty`` or ``--tcp HOST:PORT`` runs one for trying the driver without a
gripper. The simulated gripper plans a move's contact in a worker thread (tens to a few hundred
milliseconds), so the emulator's event loop keeps answering meanwhile.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import struct
import tty
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from drivers.base import DeviceError, MotionRejectedError
from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.sim.gelsight import gel_pad_spec
from drivers.sim.gripper import SimWSG50
from drivers.sim.world import SimWorld
from drivers.wsg50.protocol import (
    ACK_FAST_STOP_PAYLOAD,
    Command,
    Frame,
    FrameDecoder,
    PrePositionFlag,
    Status,
    SystemFlag,
    UpdateFlag,
    encode_reply,
)
from models.geometry import frame_from_z_axis, invert_transform, make_transform
from models.tactile.sim import GelSightSimulator

log = logging.getLogger(__name__)

CUBE_SIZE_M = 0.1
"""The bench object: a cube standing on the table at the world origin."""
MAX_ACCELERATION_MM_S2 = 5000.0
VALUE_COMMANDS = (
    Command.GET_SYSTEM_STATE,
    Command.GET_GRASP_STATE,
    Command.GET_WIDTH,
    Command.GET_SPEED,
    Command.GET_FORCE,
)
GRASP_STATE_IDLE, GRASP_STATE_POSITIONING = 0, 6


def bench_gripper(
    *,
    contact_width_m: float = 0.08,
    real_time_factor: float = 1.0,
    gripper: GripperConfig | None = None,
    sensor: SensorConfig | None = None,
) -> SimWSG50:
    """A simulated WSG 50 held with its GelSight pad facing a 10 cm cube: the gel meets the
    cube's face when the fingers open to ``contact_width_m``; wider presses the gel on it. The
    fingers start half that open, clear of the cube."""
    gripper = gripper or GripperConfig()
    sensor = sensor or SensorConfig()
    cube = trimesh.creation.box(
        (CUBE_SIZE_M,) * 3, transform=make_transform(None, (0, 0, CUBE_SIZE_M / 2))
    )
    world = SimWorld(
        cube,
        sim=SimConfig(real_time_factor=real_time_factor),
        arm=ArmConfig(),
        gripper=gripper,
        sensor=sensor,
    )
    # Pad at the middle of the face y = -size/2, gel normal +y into the cube, the finger
    # pointing down so the gripper body is above the pad.
    face_centre = np.array([0.0, -CUBE_SIZE_M / 2, CUBE_SIZE_M * 0.6])
    pose_world_pad = make_transform(frame_from_z_axis((0, 1, 0), (0, 0, -1)), face_centre)
    pose_world_tcp = pose_world_pad @ invert_transform(world.tool.pose_tcp_pad(contact_width_m))
    world.pose_base_flange = invert_transform(world.pose_world_base) @ pose_world_tcp
    world.gripper_width_m = contact_width_m / 2
    return SimWSG50(world, gripper, GelSightSimulator(gel_pad_spec(sensor)))


@dataclass
class _Link:
    """One connection to the emulator (the pty, or one TCP client)."""

    write: Callable[[bytes], object]
    decoder: FrameDecoder = field(default_factory=lambda: FrameDecoder(report_bad=True))
    outbox: asyncio.Queue[bytes] = field(default_factory=asyncio.Queue)
    updates: dict[int, asyncio.Task[None]] = field(default_factory=dict)
    tasks: list[asyncio.Task[None]] = field(default_factory=list)


class WSGEmulator:
    """The protocol engine over a ``SimWSG50``; serve it with ``serve_pty`` / ``serve_tcp``."""

    def __init__(self, gripper: SimWSG50, *, homing_opens: bool = False) -> None:
        self.gripper = gripper
        self.homing_opens = homing_opens
        """Direction of homing with payload 0 ("as configured"): the bench homes closing so
        that the cube in front of the pad does not block it."""
        self.force_limit_n = gripper.config.max_force_n
        self.acceleration_mm_s2 = 1000.0
        self.silent = False
        self.corrupt_next_reply_to: set[int] = set()
        self.chunk_size = 0
        self.received = bytearray()
        """Every byte received, for wire-level tests."""
        self.sent = bytearray()
        """Every byte sent (after fault injection), for wire-level tests."""
        self._referenced = False
        self._fast_stop = False
        self._motion: asyncio.Task[None] | None = None
        self._motion_speed_mm_s = 0.0
        self._stopped = False
        self._last_blocked_flag = SystemFlag(0)
        self._last_outcome = SystemFlag(0)
        self._force_cache: tuple[float, float] | None = None
        self._links: list[_Link] = []
        self._server: asyncio.Server | None = None
        self._pty_fds: tuple[int, int] | None = None

    # --- serving --------------------------------------------------------------------------------

    async def serve_pty(self) -> str:
        """Open a pseudo-terminal and serve on its master end; returns the device path a
        driver opens with pyserial (like /dev/ttyUSB0 on the robot)."""
        master, slave = os.openpty()
        # Raw, so that no byte is translated or echoed before pyserial sets its own mode; the
        # slave end stays open here, so the master never reads EIO between driver sessions.
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._pty_fds = (master, slave)
        link = _Link(write=lambda data: _write_fd(master, data))
        self._start_link(link, self._read_pty(link, master))
        await self.gripper.connect()
        return os.ttyname(slave)

    async def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Listen like the gripper's TCP interface; returns the bound (host, port)."""
        await self.gripper.connect()
        self._server = await asyncio.start_server(self._tcp_client, host, port)
        bound_host, bound_port = self._server.sockets[0].getsockname()[:2]
        return bound_host, bound_port

    async def close(self) -> None:
        if self._motion is not None:
            self._motion.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._motion
        for link in list(self._links):
            await self._close_link(link)
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        if self._pty_fds is not None:
            for fd in self._pty_fds:
                os.close(fd)
            self._pty_fds = None
        await self.gripper.close()

    async def _tcp_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        link = _Link(write=writer.write)

        async def read() -> None:
            while data := await reader.read(4096):
                await self._receive(link, data)

        self._start_link(link, read())
        with contextlib.suppress(asyncio.CancelledError, OSError):
            await link.tasks[0]
        await self._close_link(link)
        writer.close()

    async def _read_pty(self, link: _Link, master: int) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                readable = loop.create_future()
                loop.add_reader(master, lambda f=readable: f.done() or f.set_result(None))
                try:
                    await readable
                finally:
                    loop.remove_reader(master)
                continue
            await self._receive(link, data)

    def _start_link(self, link: _Link, reader: Coroutine[Any, Any, None]) -> None:
        self._links.append(link)
        link.tasks.append(asyncio.create_task(reader, name="wsg-emulator-read"))
        link.tasks.append(asyncio.create_task(self._write_loop(link), name="wsg-emulator-write"))

    async def _close_link(self, link: _Link) -> None:
        if link in self._links:
            self._links.remove(link)
        for task in [*link.tasks, *link.updates.values()]:
            task.cancel()
        for task in [*link.tasks, *link.updates.values()]:
            with contextlib.suppress(asyncio.CancelledError, OSError):
                await task

    async def _write_loop(self, link: _Link) -> None:
        while True:
            data = bytearray(await link.outbox.get())
            if not self.chunk_size:
                link.write(bytes(data))
                continue
            # Join what is queued within a moment, then cut it into small writes that ignore
            # frame borders.
            await asyncio.sleep(0.002)
            while not link.outbox.empty():
                data += link.outbox.get_nowait()
            for start in range(0, len(data), self.chunk_size):
                link.write(bytes(data[start : start + self.chunk_size]))
                await asyncio.sleep(0)  # lets the reader see the pieces one by one

    def _send(self, link: _Link, command: int, status: Status, params: bytes = b"") -> None:
        if self.silent:
            return
        frame = bytearray(encode_reply(command, status, params))
        if command in self.corrupt_next_reply_to:
            self.corrupt_next_reply_to.discard(command)
            frame[-1] ^= 0xFF
        self.sent += frame
        link.outbox.put_nowait(bytes(frame))

    # --- commands -------------------------------------------------------------------------------

    async def _receive(self, link: _Link, data: bytes) -> None:
        self.received += data
        for frame in link.decoder.feed(data):
            if self.silent:
                continue
            if not frame.crc_ok:
                self._send(link, frame.command, Status.CHECKSUM_ERROR)
                continue
            await self._handle(link, frame)

    async def _handle(self, link: _Link, frame: Frame) -> None:
        command, payload = frame.command, frame.payload
        if command == Command.LOOP:
            self._send(link, command, Status.SUCCESS, payload)
        elif command == Command.DISCONNECT:
            for task in link.updates.values():
                task.cancel()
            link.updates.clear()
            self._send(link, command, Status.SUCCESS)
        elif command == Command.HOMING:
            self._homing(link, payload)
        elif command == Command.PRE_POSITION:
            self._pre_position(link, payload)
        elif command in (Command.STOP, Command.FAST_STOP):
            if command == Command.FAST_STOP:
                self._fast_stop = True
            await self._stop_motion()
            self._send(link, command, Status.SUCCESS)
        elif command == Command.ACK_FAST_STOP:
            ok = payload == ACK_FAST_STOP_PAYLOAD
            self._fast_stop = self._fast_stop and not ok
            self._send(link, command, Status.SUCCESS if ok else Status.INVALID_PARAMETER)
        elif command in (Command.SET_FORCE_LIMIT, Command.SET_ACCELERATION):
            self._send(link, command, self._set_limit(command, payload))
        elif command == Command.GET_FORCE_LIMIT:
            self._send(link, command, Status.SUCCESS, struct.pack("<f", self.force_limit_n))
        elif command == Command.GET_ACCELERATION:
            self._send(link, command, Status.SUCCESS, struct.pack("<f", self.acceleration_mm_s2))
        elif command == Command.TARE_FORCE:
            self._send(link, command, Status.SUCCESS)
        elif command in VALUE_COMMANDS:
            await self._value_query(link, command, payload)
        elif command in (Command.GRASP, Command.RELEASE):
            self._send(link, command, Status.FEATURE_NOT_SUPPORTED)
        else:
            self._send(link, command, Status.CMD_UNKNOWN)

    def _motion_refusal(self) -> Status | None:
        if self._fast_stop:
            return Status.ACCESS_DENIED
        if self._motion is not None and not self._motion.done():
            return Status.ALREADY_RUNNING
        return None

    def _homing(self, link: _Link, payload: bytes) -> None:
        if len(payload) != 1:
            self._send(link, Command.HOMING, Status.CMD_FORMAT_ERROR)
            return
        if payload[0] not in (0, 1, 2):
            self._send(link, Command.HOMING, Status.INVALID_PARAMETER)
            return
        if (refusal := self._motion_refusal()) is not None:
            self._send(link, Command.HOMING, refusal)
            return
        opening = self.homing_opens if payload[0] == 0 else payload[0] == 1

        async def run() -> Status:
            try:
                await self.gripper.home(timeout_s=1e9, opening=opening)
            except MotionRejectedError:
                self._referenced = False
                return Status.AXIS_BLOCKED
            self._referenced = True
            return Status.SUCCESS

        self._start_motion(link, Command.HOMING, run(), speed_mm_s=100.0)

    def _pre_position(self, link: _Link, payload: bytes) -> None:
        if len(payload) != 9:
            self._send(link, Command.PRE_POSITION, Status.CMD_FORMAT_ERROR)
            return
        flags, width_mm, speed_mm_s = struct.unpack("<Bff", payload)
        if flags & PrePositionFlag.RELATIVE:
            width_mm += self.gripper.world.gripper_width_m * 1e3
        config = self.gripper.config
        if (refusal := self._motion_refusal()) is not None:
            self._send(link, Command.PRE_POSITION, refusal)
            return
        if not self._referenced:
            self._send(link, Command.PRE_POSITION, Status.NOT_INITIALIZED)
            return
        if not (
            0.0 <= width_mm <= config.stroke_m * 1e3
            and 0.0 < speed_mm_s <= config.max_speed_m_s * 1e3
        ):
            self._send(link, Command.PRE_POSITION, Status.RANGE_ERROR)
            return
        stop_on_block = bool(flags & PrePositionFlag.STOP_ON_BLOCK)

        async def run() -> Status:
            state = await self.gripper.move(
                width_mm * 1e-3,
                speed_m_s=speed_mm_s * 1e-3,
                force_limit_n=self.force_limit_n,
                timeout_s=1e9,
            )
            if state.blocked and stop_on_block:
                return Status.AXIS_BLOCKED
            return Status.SUCCESS

        self._start_motion(link, Command.PRE_POSITION, run(), speed_mm_s=speed_mm_s)

    def _start_motion(
        self,
        link: _Link,
        command: Command,
        run: Coroutine[Any, Any, Status],
        speed_mm_s: float,
    ) -> None:
        self._send(link, command, Status.CMD_PENDING)
        self._stopped = False
        self._motion_speed_mm_s = speed_mm_s
        opening_from_m = self.gripper.world.gripper_width_m

        async def motion() -> None:
            try:
                status = await run
            except DeviceError as error:
                log.warning("emulated motion failed: %s", error)
                status = Status.CMD_FAILED
            finally:
                self._motion_speed_mm_s = 0.0
            if self._stopped:
                status = Status.CMD_ABORTED
            opened = self.gripper.world.gripper_width_m >= opening_from_m
            self._last_blocked_flag = SystemFlag(0)
            if status == Status.AXIS_BLOCKED:
                self._last_blocked_flag = (
                    SystemFlag.BLOCKED_PLUS if opened else SystemFlag.BLOCKED_MINUS
                )
            self._last_outcome = {
                Status.SUCCESS: SystemFlag.TARGET_POS_REACHED,
                Status.CMD_ABORTED: SystemFlag.AXIS_STOPPED,
            }.get(status, SystemFlag(0))
            self._send(link, command, status)

        self._motion = asyncio.create_task(motion(), name=f"wsg-emulator-{command.name}")

    async def _stop_motion(self) -> None:
        if self._motion is not None and not self._motion.done():
            self._stopped = True
            await self.gripper.stop()

    def _set_limit(self, command: int, payload: bytes) -> Status:
        if len(payload) != 4:
            return Status.CMD_FORMAT_ERROR
        (value,) = struct.unpack("<f", payload)
        if command == Command.SET_FORCE_LIMIT:
            if not 0.0 < value <= self.gripper.config.max_force_n:
                return Status.RANGE_ERROR
            self.force_limit_n = value
        else:
            if not 0.0 < value <= MAX_ACCELERATION_MM_S2:
                return Status.RANGE_ERROR
            self.acceleration_mm_s2 = value
        return Status.SUCCESS

    # --- values ---------------------------------------------------------------------------------

    async def _value_query(self, link: _Link, command: int, payload: bytes) -> None:
        if len(payload) != 3:
            self._send(link, command, Status.CMD_FORMAT_ERROR)
            return
        flags, period_ms = struct.unpack("<BH", payload)
        old = link.updates.pop(command, None)
        if old is not None:
            old.cancel()
        if flags & UpdateFlag.AUTO and period_ms == 0:
            self._send(link, command, Status.INVALID_PARAMETER)
            return
        value = await self._value(command)
        self._send(link, command, Status.SUCCESS, value)
        if flags & UpdateFlag.AUTO:
            on_change = bool(flags & UpdateFlag.ON_CHANGE)
            link.updates[command] = asyncio.create_task(
                self._auto_update(link, command, period_ms * 1e-3, on_change, value),
                name=f"wsg-emulator-update-{command:02X}",
            )

    async def _auto_update(
        self, link: _Link, command: int, period_s: float, on_change: bool, last: bytes
    ) -> None:
        while True:
            await asyncio.sleep(period_s)
            value = await self._value(command)
            if not on_change or value != last:
                self._send(link, command, Status.SUCCESS, value)
            last = value

    async def _value(self, command: int) -> bytes:
        moving = self._motion is not None and not self._motion.done()
        if command == Command.GET_WIDTH:
            return struct.pack("<f", self.gripper.world.gripper_width_m * 1e3)
        if command == Command.GET_SPEED:
            return struct.pack("<f", self._motion_speed_mm_s if moving else 0.0)
        if command == Command.GET_FORCE:
            return struct.pack("<f", await self._force_n())
        if command == Command.GET_GRASP_STATE:
            return struct.pack("<B", GRASP_STATE_POSITIONING if moving else GRASP_STATE_IDLE)
        flags = self._last_blocked_flag | self._last_outcome
        if self._referenced:
            flags |= SystemFlag.REFERENCED
        if moving:
            flags = SystemFlag.MOVING | (flags & SystemFlag.REFERENCED)
        if self._fast_stop:
            flags |= SystemFlag.FAST_STOP
        return struct.pack("<I", flags)

    async def _force_n(self) -> float:
        """Gel force at the current opening; ray casting costs milliseconds, so it is cached
        per opening."""
        width_m = self.gripper.world.gripper_width_m
        if self._force_cache is None or self._force_cache[0] != width_m:
            state = await self.gripper.state()
            self._force_cache = (width_m, state.force_n)
        return self._force_cache[1]


def _write_fd(fd: int, data: bytes) -> None:
    try:
        os.write(fd, data)
    except BlockingIOError:
        # Nobody reads the line (the driver is gone): a real gripper's bytes are lost too.
        log.debug("pty full: dropped %d bytes", len(data))
