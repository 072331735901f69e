"""The UR controller emulator at the wire (RTDE, dashboard), then driven by the real ur-rtde
client: its constructors hold the GIL while they wait for the controller, so the client runs
in a subprocess while the emulator serves from the test's event loop."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import struct
import sys

import numpy as np
import pytest

from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.sim.ur_emulator import (
    CONTROLLER_VERSION,
    DASHBOARD_PORT,
    RTDE_PORT,
    Command,
    URControllerEmulator,
)
from drivers.sim.world import SimWorld
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import matrix_to_ur_pose

_host_numbers = itertools.count(2)


def loopback_host() -> str:
    """A loopback address of its own for each emulator: ur-rtde's ports are fixed."""
    return f"127.{50 + os.getpid() % 200}.{next(_host_numbers)}.1"


def make_emulator(real_time_factor: float) -> URControllerEmulator:
    arm = ArmConfig(type="ur_rtde", host=loopback_host())
    sim = SimConfig(real_time_factor=real_time_factor)
    world = SimWorld.from_config(sim, arm, GripperConfig(), SensorConfig())
    return URControllerEmulator(world, arm)


async def rtde_exchange(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, kind: str, payload: bytes = b""
) -> tuple[str, bytes]:
    writer.write(struct.pack(">HB", 3 + len(payload), ord(kind)) + payload)
    await writer.drain()
    return await rtde_message(reader)


async def rtde_message(reader: asyncio.StreamReader) -> tuple[str, bytes]:
    size, kind = struct.unpack(">HB", await reader.readexactly(3))
    return chr(kind), await reader.readexactly(size - 3)


async def test_rtde_handshake_recipes_and_data_packages() -> None:
    async with make_emulator(real_time_factor=1.0) as controller:
        reader, writer = await asyncio.open_connection(controller.host, RTDE_PORT)
        assert await rtde_exchange(reader, writer, "V", struct.pack(">H", 3)) == ("V", b"\x00")
        assert await rtde_exchange(reader, writer, "V", struct.pack(">H", 2)) == ("V", b"\x01")
        kind, body = await rtde_exchange(reader, writer, "v")
        assert kind == "v" and struct.unpack(">4I", body) == CONTROLLER_VERSION

        names = b"timestamp,actual_q,runtime_state,no_such_variable"
        kind, body = await rtde_exchange(reader, writer, "O", struct.pack(">d", 125.0) + names)
        assert body[1:] == b"DOUBLE,VECTOR6D,UINT32,NOT_FOUND"
        kind, body = await rtde_exchange(reader, writer, "S")
        assert (kind, body) == ("S", b"\x00")  # refused: an output is not found

        kind, body = await rtde_exchange(
            reader, writer, "O", struct.pack(">d", 125.0) + b"timestamp,actual_q,runtime_state"
        )
        assert body == b"\x01DOUBLE,VECTOR6D,UINT32"
        kind, body = await rtde_exchange(reader, writer, "I", b"input_int_register_0")
        assert body == b"\x01INT32"
        names = b"input_int_register_0,input_double_register_3,external_force_torque"
        kind, body = await rtde_exchange(reader, writer, "I", names)
        assert body == b"\x02INT32,DOUBLE,VECTOR6D"
        assert await rtde_exchange(reader, writer, "S") == ("S", b"\x01")

        timestamps = []
        for _ in range(3):
            kind, body = await rtde_message(reader)
            assert kind == "U" and len(body) == 1 + 8 + 48 + 4
            recipe, timestamp, *joints, runtime_state = struct.unpack(">Bd6dI", body)
            assert recipe == 1 and runtime_state == 1  # no program yet: stopped
            np.testing.assert_allclose(joints, controller.world.joints_rad)
            timestamps.append(timestamp)
        assert timestamps == sorted(timestamps) and timestamps[0] < timestamps[-1]

        data = struct.pack(">Bid6d", 2, 42, 0.5, *range(6))
        writer.write(struct.pack(">HB", 3 + len(data), ord("U")) + data)
        writer.write(struct.pack(">HB", 3, ord("P")))
        await writer.drain()
        while (message := await rtde_message(reader))[0] == "U":
            pass  # data packages sent before the pause was read
        assert message == ("P", b"\x01")
        assert controller.inputs["input_int_register_0"] == 42
        assert controller.inputs["input_double_register_3"] == 0.5
        assert controller.inputs["external_force_torque"] == (0, 1, 2, 3, 4, 5)
        writer.close()


async def test_dashboard_answers_like_polyscope() -> None:
    async with make_emulator(real_time_factor=1.0) as controller:
        reader, writer = await asyncio.open_connection(controller.host, DASHBOARD_PORT)
        assert await reader.readline() == b"Connected: Universal Robots Dashboard Server\n"
        answers = {}
        for command in (
            "PolyscopeVersion",
            "robotmode",
            "safetystatus",
            "programState",
            "unlock protective stop",
            "no such command",
        ):
            writer.write(command.encode() + b"\n")
            answers[command] = (await reader.readline()).decode().strip()
        assert answers["PolyscopeVersion"].startswith("URSoftware 3.15.8.106339")
        assert answers["robotmode"] == "Robotmode: RUNNING"
        assert answers["safetystatus"] == "Safetystatus: NORMAL"
        assert answers["programState"] == "STOPPED <unnamed>"
        assert answers["unlock protective stop"] == "Protective stop releasing"
        assert answers["no such command"] == "could not understand: 'no such command'"
        writer.close()


REAL_TIME_FACTOR = 0.2
"""The emulator's simulated time runs 5x faster than the wall clock in the client test."""

CLIENT = """
import json, sys, time
import dashboard_client, rtde_control, rtde_receive

host, hold_s = sys.argv[1], float(sys.argv[2])
out = {}
receive = rtde_receive.RTDEReceiveInterface(host)  # ur-rtde's full default output recipe
control = rtde_control.RTDEControlInterface(host)  # uploads the control script
dashboard = dashboard_client.DashboardClient(host)
dashboard.connect()
start = receive.getActualTCPPose()
out["start_pose"], out["start_q"] = start, receive.getActualQ()
out["program_running"] = control.isProgramRunning()
down = list(start)
down[2] -= 0.04
out["movel"] = control.moveL(down, 0.2, 1.0)
time.sleep(0.02)  # the receive interface's next data package
out["after_movel"] = receive.getActualTCPPose()
out["movel_async"] = control.moveL(start, 0.005, 1.0, True)
time.sleep(0.3)
out["running_during"] = control.getAsyncOperationProgressEx().isAsyncOperationRunning()
control.stopL(2.0)
out["running_after_stop"] = control.getAsyncOperationProgressEx().isAsyncOperationRunning()
time.sleep(0.02)
out["after_stop"] = receive.getActualTCPPose()
time.sleep(0.1)
out["later"] = receive.getActualTCPPose()
low = list(start)
low[2] = -0.3
out["movel_into_table"] = control.moveL(low, 0.25, 1.2)
time.sleep(0.05)
out["protective_stopped"] = receive.isProtectiveStopped()
out["safety_status"] = dashboard.safetystatus()
try:
    dashboard.unlockProtectiveStop()
except RuntimeError as error:  # ur-rtde 1.6 raises when the controller refuses
    out["early_unlock"] = str(error)
out["stopped_after_early_unlock"] = receive.isProtectiveStopped()
time.sleep(hold_s)
dashboard.unlockProtectiveStop()
dashboard.closeSafetyPopup()
time.sleep(0.05)
out["stopped_after_unlock"] = receive.isProtectiveStopped()
out["reupload"] = control.reuploadScript()
deadline = time.monotonic() + 2.0
while not control.isProgramRunning() and time.monotonic() < deadline:
    time.sleep(0.01)
out["movel_after_recovery"] = control.moveL(start, 0.25, 1.2)
time.sleep(0.02)
out["final_pose"] = receive.getActualTCPPose()
out["speedl"] = control.speedL([0.0, 0.0, 0.02, 0.0, 0.0, 0.0], 0.5)
time.sleep(0.3)
out["speedl_z"] = receive.getActualTCPPose()[2]
out["speed_stop"] = control.speedStop(2.0)
time.sleep(0.02)
out["speed_stop_z"] = receive.getActualTCPPose()[2]
time.sleep(0.1)
out["later_z"] = receive.getActualTCPPose()[2]
control.triggerProtectiveStop()
time.sleep(0.02)
out["triggered_stop"] = receive.isProtectiveStopped()
control.stopScript()
control.disconnect()
receive.disconnect()
dashboard.disconnect()
print("RESULT " + json.dumps(out))
"""


async def test_real_ur_rtde_client_moves_stops_and_recovers() -> None:
    async with make_emulator(REAL_TIME_FACTOR) as controller:
        hold_wall_s = 5.0 * REAL_TIME_FACTOR + 0.2
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-c",
            CLIENT,
            controller.host,
            str(hold_wall_s),
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
        )
        output, _ = await asyncio.wait_for(process.communicate(), timeout=60)
        text = output.decode(errors="replace")
        assert process.returncode == 0, text
        result = json.loads(text.split("RESULT ", 1)[1])

    world_pose_at_start = matrix_to_ur_pose(forward_kinematics(result["start_q"]))
    np.testing.assert_allclose(result["start_pose"], world_pose_at_start, atol=1e-9)
    assert result["program_running"]
    assert "RTDE Control Script" in controller.scripts_received[0]

    assert result["movel"] is True
    expected = np.array(result["start_pose"]) - [0, 0, 0.04, 0, 0, 0]
    np.testing.assert_allclose(result["after_movel"], expected, atol=1e-6)

    assert result["movel_async"] is True and result["running_during"]
    assert not result["running_after_stop"]
    stopped_z = result["after_stop"][2]
    assert expected[2] + 1e-3 < stopped_z < result["start_pose"][2] - 2e-4  # stopped partway
    np.testing.assert_allclose(result["later"], result["after_stop"], atol=1e-9)

    assert result["movel_into_table"] is False  # ur-rtde reports the protective stop
    assert result["protective_stopped"]
    assert result["safety_status"] == "Safetystatus: PROTECTIVE_STOP"
    assert "Cannot unlock protective stop until 5s after occurrence" in result["early_unlock"]
    assert result["stopped_after_early_unlock"]
    assert not result["stopped_after_unlock"]
    assert result["reupload"] is True
    assert result["movel_after_recovery"] is True
    np.testing.assert_allclose(result["final_pose"], result["start_pose"], atol=1e-6)

    assert result["speedl"] is True and result["speed_stop"] is True
    assert result["speedl_z"] > result["final_pose"][2] + 1e-3  # moving up
    assert result["speedl_z"] <= result["speed_stop_z"] == result["later_z"]
    assert result["triggered_stop"]

    assert len(controller.scripts_received) == 2  # the upload and the re-upload
    moves_and_stops = [c for c in controller.commands_received if c != Command.NONE]
    assert moves_and_stops == [
        Command.MOVEL,
        Command.MOVEL,
        Command.STOPL,
        Command.MOVEL,
        Command.MOVEL,
        Command.SPEEDL,
        Command.SPEED_STOP,
        Command.PROTECTIVE_STOP,  # then stopScript is refused: no program runs
    ]


def test_emulator_needs_real_time() -> None:
    with pytest.raises(ValueError, match="real_time_factor"):
        make_emulator(real_time_factor=0.0)
