"""The WSG 50 driver against the protocol emulator, over a pty (pyserial) and over TCP.

The emulator runs the simulated gripper with its pad facing a cube: the gel meets the cube at
a 20 mm opening, so opening further blocks the axis on the force limit. Openings are kept small
because the simulated gripper's contact planning costs CPU per millimetre travelled.
"""

from __future__ import annotations

import asyncio
import struct
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import pytest
import serial

from drivers.base import (
    DeviceConnectionError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    MotionRejectedError,
)
from drivers.config import GripperConfig
from drivers.sim.wsg50_emulator import WSGEmulator, bench_gripper
from drivers.wsg50.gripper import WSG50Gripper
from drivers.wsg50.protocol import (
    Command,
    FrameDecoder,
    Reply,
    Status,
    SystemFlag,
    UpdateFlag,
    WSGRejectedError,
    encode_frame,
    encode_reply,
    update_payload,
)

CONTACT_WIDTH_M = 0.02
LINKS = ["pty", "tcp"]


@asynccontextmanager
async def emulated(
    link: str, *, real_time_factor: float = 0.0, **config: float
) -> AsyncIterator[tuple[WSGEmulator, GripperConfig]]:
    """A bench emulator served on ``link`` and a driver config pointing at it.

    The emulator shares the test's event loop, and the simulated gripper plans a move's contact
    on it (up to a few hundred ms on a loaded machine), delaying its automatic updates: the
    state may be older than on a real gripper.
    """
    config.setdefault("max_state_age_s", 1.0)
    emulator = WSGEmulator(
        bench_gripper(contact_width_m=CONTACT_WIDTH_M, real_time_factor=real_time_factor)
    )
    if link == "pty":
        path = await emulator.serve_pty()
        gripper_config = GripperConfig(type="wsg50_serial", serial_port=path, **config)
    else:
        host, port = await emulator.serve_tcp("127.0.0.1", 0)
        gripper_config = GripperConfig(type="wsg50_tcp", host=host, tcp_port=port, **config)
    try:
        yield emulator, gripper_config
    finally:
        await emulator.close()


@asynccontextmanager
async def connected(
    link: str, *, real_time_factor: float = 0.0, home: bool = True, **config: float
) -> AsyncIterator[tuple[WSGEmulator, WSG50Gripper]]:
    async with emulated(link, real_time_factor=real_time_factor, **config) as (emulator, cfg):
        gripper = WSG50Gripper(cfg)
        await gripper.connect()
        try:
            if home:
                await gripper.home(timeout_s=5.0)
            yield emulator, gripper
        finally:
            await gripper.close()


async def until(condition: Callable[[], bool], timeout_s: float = 2.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.01)


async def wait_for_bytes(emulator: WSGEmulator, *, ending: bytes) -> None:
    """Until the emulator has read bytes ending with ``ending`` (it reads asynchronously)."""
    async with asyncio.timeout(2.0):
        while not emulator.received.endswith(ending):
            await asyncio.sleep(0.01)


def frames(data: bytes) -> list[tuple[int, bytes]]:
    return [(f.command, f.payload) for f in FrameDecoder().feed(bytes(data))]


# --- the wire -------------------------------------------------------------------------------------


async def test_wire_bytes_of_connect_homing_pre_position_and_force_readback() -> None:
    async with emulated("pty") as (emulator, config):
        gripper = WSG50Gripper(config)
        await gripper.connect()
        await gripper.home()
        state = await gripper.move(0.015, speed_m_s=0.05, force_limit_n=5.0, timeout_s=5.0)
        assert not state.blocked and state.width_m == pytest.approx(0.015)
        await gripper.close()
        await wait_for_bytes(emulator, ending=bytes.fromhex("aa aa aa 07 00 00 35 4c"))
    sent_by_driver = bytes.fromhex(
        # connect: loop echo, automatic updates of state, width and force every 20 ms,
        # read the force limit
        "aa aa aa 06 0a 00 74 6f 75 63 68 73 68 61 70 65 2b 12"
        "aa aa aa 40 03 00 01 14 00 7b ed"
        "aa aa aa 43 03 00 01 14 00 36 8d"
        "aa aa aa 45 03 00 01 14 00 99 7e"
        "aa aa aa 33 00 00 2c 70"
        # homing (0x20, direction 0 = as configured)
        "aa aa aa 20 01 00 00 8f 83"
        # force limit 5.0 N (0x32), pre-position (0x21): stop on block, 15.0 mm at 50.0 mm/s
        "aa aa aa 32 04 00 00 00 a0 40 d4 32"
        "aa aa aa 21 09 00 02 00 00 70 41 00 00 48 42 fd f1"
        # close: automatic updates off, disconnect
        "aa aa aa 40 03 00 00 00 00 f5 70"
        "aa aa aa 43 03 00 00 00 00 b8 10"
        "aa aa aa 45 03 00 00 00 00 17 e3"
        "aa aa aa 07 00 00 35 4c"
    )
    assert bytes(emulator.received) == sent_by_driver
    replies = frames(emulator.sent)
    # Force readback: the first 0x45 reply is 0.0 N (no contact), status 0.
    first_force = bytes(emulator.sent).index(bytes.fromhex("aa aa aa 45"))
    assert bytes(emulator.sent)[first_force : first_force + 14] == bytes.fromhex(
        "aa aa aa 45 06 00 00 00 00 00 00 00 76 dd"
    )
    # Homing and pre-position: CMD_PENDING (26) first, then SUCCESS, on the wire.
    pending, done = encode_reply(0x20, Status.CMD_PENDING), encode_reply(0x20, Status.SUCCESS)
    assert pending == bytes.fromhex("aa aa aa 20 02 00 1a 00 fc 32")
    assert done == bytes.fromhex("aa aa aa 20 02 00 00 00 b3 fd")
    motion = [(c, p) for c, p in replies if c in (0x20, 0x21)]
    assert motion == [
        (0x20, b"\x1a\x00"),
        (0x20, b"\x00\x00"),
        (0x21, b"\x1a\x00"),
        (0x21, b"\x00\x00"),
    ]


async def test_force_readback_on_contact_reaches_the_driver_bit_exact() -> None:
    async with connected("pty") as (emulator, gripper):
        await gripper.move(0.015, speed_m_s=0.05, force_limit_n=5.0, timeout_s=5.0)
        state = await gripper.move(0.03, speed_m_s=0.01, force_limit_n=5.0, timeout_s=5.0)
        forces = [
            struct.unpack("<f", p[2:])[0]
            for c, p in frames(emulator.sent)
            if c == Command.GET_FORCE
        ]
    assert state.blocked
    assert state.force_n == pytest.approx(5.0, rel=0.1)
    assert state.force_n in forces  # the f32 the emulator put on the wire, unchanged
    assert forces[0] == 0.0


async def test_a_frame_with_a_bad_crc_is_answered_with_checksum_error() -> None:
    async with emulated("pty") as (_, config):
        port = serial.Serial(config.serial_port, 115200, timeout=1.0)
        try:
            bad = bytearray(encode_frame(Command.HOMING, b"\x00"))
            bad[-1] ^= 0xFF
            port.write(bytes(bad))
            expected = encode_reply(Command.HOMING, Status.CHECKSUM_ERROR)
            assert expected == bytes.fromhex("aa aa aa 20 02 00 0b 00 cf 20")
            reply = await asyncio.to_thread(port.read, len(expected))
        finally:
            port.close()
    assert reply == expected


async def test_automatic_updates_on_change_only() -> None:
    async with emulated("pty") as (_, config):
        port = serial.Serial(config.serial_port, 115200, timeout=0.3)
        try:
            on_change = UpdateFlag.AUTO | UpdateFlag.ON_CHANGE
            port.write(encode_frame(Command.GET_WIDTH, update_payload(on_change, 10)))
            received = await asyncio.to_thread(port.read, 1000)  # 0.3 s of a still gripper
        finally:
            port.close()
    # The immediate reply only: 10 mm, status 0 (the bench starts half its 20 mm open).
    assert frames(received) == [(Command.GET_WIDTH, b"\x00\x00" + struct.pack("<f", 10.0))]


# --- the emulator suite, over both links ----------------------------------------------------------


@pytest.mark.parametrize("link", LINKS)
async def test_normal_operation(link: str) -> None:
    async with connected(link) as (_, gripper):
        assert gripper.is_connected
        assert SystemFlag.REFERENCED in gripper.system_flags
        assert (await gripper.state()).width_m == pytest.approx(0.0)  # homed closing
        state = await gripper.move(0.015, speed_m_s=0.1, force_limit_n=20.0, timeout_s=5.0)
        assert state.width_m == pytest.approx(0.015, abs=1e-4)
        assert not state.blocked and not state.is_moving and state.force_n == 0.0
        assert gripper.force_limit_n == 20.0
        assert (await gripper.state()).width_m == pytest.approx(0.015, abs=1e-4)
    assert not gripper.is_connected
    await gripper.close()  # twice is fine
    with pytest.raises(DeviceNotConnectedError):
        await gripper.state()


@pytest.mark.parametrize("link", LINKS)
async def test_blocked_axis_on_contact(link: str) -> None:
    async with connected(link) as (_, gripper):
        await gripper.move(0.015, speed_m_s=0.1, force_limit_n=4.0, timeout_s=5.0)
        state = await gripper.move(0.03, speed_m_s=0.01, force_limit_n=4.0, timeout_s=5.0)
        assert state.blocked
        assert state.force_n == pytest.approx(4.0, rel=0.1)
        # Stopped within the gel's 1.5 mm of indentation past the contact opening.
        assert CONTACT_WIDTH_M < state.width_m < CONTACT_WIDTH_M + 2 * 1.5e-3
        assert SystemFlag.BLOCKED_PLUS in gripper.system_flags
        # Closing again frees the axis.
        state = await gripper.move(0.01, speed_m_s=0.1, force_limit_n=4.0, timeout_s=5.0)
        assert not state.blocked and state.force_n == 0.0


@pytest.mark.parametrize("link", LINKS)
@pytest.mark.parametrize("chunk_size", [3, 64])
async def test_partial_and_interleaved_frames(link: str, chunk_size: int) -> None:
    """Replies arrive split across writes, several per write, between automatic updates."""
    async with emulated(link, state_update_period_ms=10) as (emulator, config):
        emulator.chunk_size = chunk_size
        gripper = WSG50Gripper(config)
        read_sizes = []
        transport_read = gripper.transport.read

        async def recording_read() -> bytes:
            data = await transport_read()
            read_sizes.append(len(data))
            return data

        gripper.transport.read = recording_read  # type: ignore[method-assign]
        await gripper.connect()
        try:
            await gripper.home()
            await gripper.move(0.015, speed_m_s=0.1, force_limit_n=5.0, timeout_s=5.0)
            state = await gripper.move(0.03, speed_m_s=0.01, force_limit_n=5.0, timeout_s=5.0)
            assert state.blocked and state.force_n == pytest.approx(5.0, rel=0.1)
        finally:
            await gripper.close()
    shortest_frame = 10  # a reply with a status only
    if chunk_size < shortest_frame:
        assert min(read_sizes) < shortest_frame  # frames arrived in pieces
    else:
        assert max(read_sizes) > 2 * shortest_frame  # several frames in one read
    assert gripper._decoder.crc_errors == 0


@pytest.mark.parametrize("link", LINKS)
async def test_corrupted_reply_times_out_then_the_link_resyncs(link: str) -> None:
    async with connected(link, timeout_s=0.3) as (emulator, gripper):
        emulator.corrupt_next_reply_to = {Command.GET_FORCE_LIMIT}
        with pytest.raises(DeviceTimeoutError, match="bad CRC"):
            await gripper.command(Command.GET_FORCE_LIMIT)
        assert (await gripper.command(Command.GET_FORCE_LIMIT)).float_value() == 80.0
        await gripper.stop()


@pytest.mark.parametrize("link", LINKS)
async def test_unknown_command_is_rejected_and_the_link_stays_up(link: str) -> None:
    async with connected(link, home=False) as (_, gripper):
        with pytest.raises(WSGRejectedError) as caught:
            await gripper.command(0x7F)
        assert caught.value.status == Status.CMD_UNKNOWN
        with pytest.raises(WSGRejectedError) as caught:
            await gripper.move(0.015, speed_m_s=0.1, force_limit_n=5.0, timeout_s=2.0)
        assert caught.value.status == Status.NOT_INITIALIZED
        echo = await gripper.command(Command.LOOP, b"\x01\x02")
        assert echo.params == b"\x01\x02"


@pytest.mark.parametrize("link", LINKS)
async def test_device_timeout_when_the_gripper_goes_silent(link: str) -> None:
    async with connected(link, timeout_s=0.3, max_state_age_s=0.1) as (emulator, gripper):
        emulator.silent = True
        await asyncio.sleep(0.15)
        with pytest.raises(DeviceTimeoutError, match="no state update"):
            await gripper.state()
        started = time.monotonic()
        with pytest.raises(DeviceTimeoutError, match="did not answer 0x22"):
            await gripper.stop()
        assert time.monotonic() - started < 0.6
        with pytest.raises(DeviceTimeoutError):
            await gripper.move(0.05, speed_m_s=0.1, force_limit_n=80.0, timeout_s=1.0)
        emulator.silent = False
        await gripper.stop()


@pytest.mark.parametrize("link", LINKS)
async def test_stop_ends_a_move_short_of_its_width(link: str) -> None:
    async with connected(link, real_time_factor=1.0) as (emulator, gripper):
        move = asyncio.create_task(
            gripper.move(0.019, speed_m_s=0.005, force_limit_n=5.0, timeout_s=10.0)
        )
        async with asyncio.timeout(3.0):
            while (await gripper.state()).width_m < 0.004:
                await asyncio.sleep(0.01)
        assert (await gripper.state()).is_moving
        await gripper.stop()
        state = await move
        assert not state.blocked and not state.is_moving
        assert 0.004 <= state.width_m < 0.015
        assert SystemFlag.AXIS_STOPPED in gripper.system_flags
        assert (0x21, struct.pack("<H", Status.CMD_ABORTED)) in frames(emulator.sent)


@pytest.mark.parametrize("link", LINKS)
async def test_timeout_and_cancel_stop_the_fingers(link: str) -> None:
    async with connected(link, real_time_factor=1.0) as (emulator, gripper):
        with pytest.raises(DeviceTimeoutError, match="0x21"):
            await gripper.move(0.019, speed_m_s=0.01, force_limit_n=5.0, timeout_s=0.2)
        await until(lambda: (Command.STOP, b"") in frames(emulator.received))
        move = asyncio.create_task(
            gripper.move(0.019, speed_m_s=0.005, force_limit_n=5.0, timeout_s=10.0)
        )
        await asyncio.sleep(0.1)
        stops = frames(emulator.received).count((Command.STOP, b""))
        move.cancel()
        with pytest.raises(asyncio.CancelledError):
            await move
        await until(lambda: frames(emulator.received).count((Command.STOP, b"")) == stops + 1)
        await asyncio.sleep(0.1)
        assert not (await gripper.state()).is_moving


@pytest.mark.parametrize("link", LINKS)
async def test_fast_stop_refuses_motion_until_acknowledged(link: str) -> None:
    async with connected(link) as (_, gripper):
        await gripper.fast_stop()
        with pytest.raises(WSGRejectedError) as caught:
            await gripper.move(0.015, speed_m_s=0.1, force_limit_n=5.0, timeout_s=2.0)
        assert caught.value.status == Status.ACCESS_DENIED
        await asyncio.sleep(0.05)
        assert SystemFlag.FAST_STOP in gripper.system_flags
        await gripper.acknowledge_fast_stop()
        state = await gripper.move(0.015, speed_m_s=0.1, force_limit_n=5.0, timeout_s=2.0)
        assert state.width_m == pytest.approx(0.015, abs=1e-4)
        assert SystemFlag.FAST_STOP not in gripper.system_flags


async def test_limits_are_checked_before_anything_is_sent() -> None:
    async with connected("pty") as (emulator, gripper):
        sent = len(emulator.received)
        for width, speed, force in [(0.2, 0.1, 5.0), (0.05, 1.0, 5.0), (0.05, 0.1, 200.0)]:
            with pytest.raises(MotionRejectedError):
                await gripper.move(width, speed_m_s=speed, force_limit_n=force, timeout_s=1.0)
        assert len(emulator.received) == sent


@pytest.mark.parametrize("link", LINKS)
async def test_lost_link_fails_the_waiting_request(link: str) -> None:
    async with emulated(link, real_time_factor=1.0) as (emulator, config):
        gripper = WSG50Gripper(config)
        await gripper.connect()
        await gripper.home()
        move = asyncio.create_task(
            gripper.move(0.019, speed_m_s=0.005, force_limit_n=5.0, timeout_s=10.0)
        )
        await asyncio.sleep(0.1)
        await emulator.close()  # like unplugging the adapter or dropping the connection
        with pytest.raises(DeviceConnectionError):
            await asyncio.wait_for(move, 5.0)
        assert not gripper.is_connected
        await gripper.close()


def test_reply_parsing_of_the_system_state() -> None:
    reply = Reply(0x40, 0, struct.pack("<I", 0b1_0000_0000_1001))
    assert (
        reply.system_flags()
        == SystemFlag.REFERENCED | SystemFlag.BLOCKED_PLUS | SystemFlag.FAST_STOP
    )
