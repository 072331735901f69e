"""UR controller emulator: the network face of a UR5 controller, backed by the simulated arm.

It speaks what the real ur-rtde client (and the ``ur_rtde`` arm driver over it) uses, so that
client runs unchanged against the simulated bench:

- RTDE protocol v2 on port 30004: protocol version, controller version, output and input
  recipe setup (variable names -> types, ``NOT_FOUND`` for unknown ones), start / pause, and
  output data packages streamed at the frequency each client asked for; input data packages
  write the controller's input registers.
- The dashboard server on port 29999 (the commands ur-rtde's ``DashboardClient`` sends).
- The script port 30003 that receives ur-rtde's control script. The script is not parsed as
  URScript: the emulator recognises ur-rtde's control script and runs its register handshake
  (``input_int_register_0`` command, ``output_int_register_0`` ready / done, the async-progress
  word in ``output_int_register_2``) for moveJ and moveL (blocking and asynchronous), speedL,
  stopJ, stopL, speedStop, triggerProtectiveStop and stopScript. Other commands are acknowledged
  without effect and logged, as the real script does for commands it does not know.

Motions run through ``SimUR5`` in simulated time paced at ``real_time_factor`` (must be > 0):
straight lines with trapezoidal profiles, joint limits, and a protective stop when the tool
hits the object or the table. A protective stop pauses the control program and sets the
safety bits; the dashboard unlocks it only 5 s (controller time) after it happened, as a UR
does. While the arm is idle the simulated clock follows the wall clock, so those 5 s pass.

ur-rtde's ports are fixed, so each emulator binds its own loopback address (127.0.0.2, ...).
The emulated controller reports PolyScope / controller version 3.15 (a CB3 UR5): ur-rtde then
skips the remote-control check and uses 125 Hz unless told otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import enum
import logging
import re
import struct
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from drivers.base import MotionRejectedError, ProtectiveStopError
from drivers.config import ArmConfig
from drivers.sim.arm import PROTECTIVE_STOP_HOLD_S, SimUR5
from drivers.sim.world import SimWorld
from drivers.ur5.kinematics import inverse_kinematics
from models.geometry import invert_transform, matrix_to_ur_pose, ur_pose_to_matrix

log = logging.getLogger(__name__)

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
CONTROLLER_VERSION = (3, 15, 8, 106339)
"""major, minor, bugfix, build: a CB3 controller with PolyScope 3.15."""
ROBOT_MODEL = "UR5"

# RTDE message types (ASCII letters) and the protocol version served.
RTDE_REQUEST_PROTOCOL_VERSION = ord("V")
RTDE_GET_URCONTROL_VERSION = ord("v")
RTDE_TEXT_MESSAGE = ord("M")
RTDE_DATA_PACKAGE = ord("U")
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
RTDE_CONTROL_PACKAGE_START = ord("S")
RTDE_CONTROL_PACKAGE_PAUSE = ord("P")
RTDE_PROTOCOL_VERSION = 2

RTDE_TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
"""RTDE type names and their big-endian struct codes."""

REGISTER_COUNT = 48
_VECTOR6D = [
    "target_q",
    "target_qd",
    "target_qdd",
    "target_current",
    "target_moment",
    "actual_q",
    "actual_qd",
    "actual_current",
    "joint_control_output",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "actual_TCP_force",
    "target_TCP_pose",
    "target_TCP_speed",
    "joint_temperatures",
    "actual_joint_voltage",
    "payload_inertia",
    "ft_raw_wrench",
]
_DOUBLE = [
    "timestamp",
    "actual_execution_time",
    "speed_scaling",
    "target_speed_fraction",
    "actual_momentum",
    "actual_main_voltage",
    "actual_robot_voltage",
    "actual_robot_current",
    "standard_analog_input0",
    "standard_analog_input1",
    "standard_analog_output0",
    "standard_analog_output1",
    "io_current",
    "tool_analog_input0",
    "tool_analog_input1",
    "tool_output_current",
    "tool_temperature",
    "tcp_force_scalar",
    "payload",
]
OUTPUT_TYPES: dict[str, str] = {
    **dict.fromkeys(_VECTOR6D, "VECTOR6D"),
    **dict.fromkeys(_DOUBLE, "DOUBLE"),
    **dict.fromkeys(
        ["actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog"],
        "VECTOR3D",
    ),
    **dict.fromkeys(["actual_digital_input_bits", "actual_digital_output_bits"], "UINT64"),
    **dict.fromkeys(["robot_mode", "safety_mode", "safety_status", "tool_output_voltage"], "INT32"),
    **dict.fromkeys(
        [
            "runtime_state",
            "robot_status_bits",
            "safety_status_bits",
            "analog_io_types",
            "tool_mode",
            "tool_analog_input_types",
            "output_bit_registers0_to_31",
            "output_bit_registers32_to_63",
        ],
        "UINT32",
    ),
    "joint_mode": "VECTOR6INT32",
    **{f"output_int_register_{i}": "INT32" for i in range(REGISTER_COUNT)},
    **{f"output_double_register_{i}": "DOUBLE" for i in range(REGISTER_COUNT)},
}
"""Output variables served (names and types from UR's RTDE guide); unknown ones: NOT_FOUND."""
INPUT_TYPES: dict[str, str] = {
    **{f"input_int_register_{i}": "INT32" for i in range(REGISTER_COUNT)},
    **{f"input_double_register_{i}": "DOUBLE" for i in range(REGISTER_COUNT)},
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    **dict.fromkeys(
        [
            "standard_digital_output_mask",
            "standard_digital_output",
            "configurable_digital_output_mask",
            "configurable_digital_output",
            "tool_digital_output_mask",
            "tool_digital_output",
            "standard_analog_output_mask",
            "standard_analog_output_type",
        ],
        "UINT8",
    ),
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
}

# Controller states as RTDE reports them.
ROBOT_MODE_RUNNING = 7
JOINT_MODE_RUNNING = 253
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3
RUNTIME_STOPPED = 1
RUNTIME_PLAYING = 2
RUNTIME_PAUSED = 4
ROBOT_STATUS_POWER_ON = 1 << 0
ROBOT_STATUS_PROGRAM_RUNNING = 1 << 1
SAFETY_STATUS_NORMAL = 1 << 0
SAFETY_STATUS_PROTECTIVE_STOPPED = 1 << 2


class Command(enum.IntEnum):
    """ur-rtde control-script commands (``input_int_register_0``) the emulator executes."""

    NONE = 0
    MOVEJ = 1
    MOVEL = 3
    SPEEDL = 10
    SPEED_STOP = 15
    PROTECTIVE_STOP = 31
    STOPL = 33
    STOPJ = 34
    STOP_SCRIPT = 255


REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58})
"""Commands the script processes every cycle without the ready/done handshake."""
SIGNAL_READY = 1
SIGNAL_DONE = 2
CONTROL_SCRIPT_MARKER = "RTDE Control Script"
"""Text in ur-rtde's control script (its textmsg on start); other scripts are not run."""
MOVE_TIMEOUT_S = 3600.0
"""SimUR5 needs a timeout; the UR controller has none for a single move."""


@dataclass
class _Snapshot:
    """The controller's state at one control tick (base frame, SI units)."""

    time_s: float
    joints: NDArray[np.float64]
    joint_speeds: NDArray[np.float64]
    pose_tcp: NDArray[np.float64]
    tcp_speed: NDArray[np.float64]


class URControllerEmulator:
    """A UR5 controller on ``host`` (RTDE, dashboard and script ports) moving a ``SimUR5``.

    Use as ``async with URControllerEmulator(world, config, host="127.0.0.2") as controller:``.
    ``world.clock.real_time_factor`` must be > 0: 1.0 moves in real time, 0.2 five times
    faster (tests), 2.0 at half speed.
    """

    def __init__(self, world: SimWorld, config: ArmConfig, *, host: str | None = None) -> None:
        if world.clock.real_time_factor <= 0.0:
            raise ValueError("the UR controller emulator needs sim.real_time_factor > 0")
        self.world = world
        self.host = host or config.host
        self.arm = SimUR5(world, config)
        self.period_s = 1.0 / config.control_frequency_hz
        self._pose_flange_tcp = ur_pose_to_matrix(config.tcp_offset)
        self._pose_tcp_flange = invert_transform(self._pose_flange_tcp)
        self.inputs: dict[str, object] = {}
        """Input variables as the RTDE clients last wrote them."""
        self.output_int = [0] * REGISTER_COUNT
        self.output_double = [0.0] * REGISTER_COUNT
        self.runtime_state = RUNTIME_STOPPED
        self.scripts_received: list[str] = []
        """Every program received on the script port, in order (for inspection)."""
        self.commands_received: list[int] = []
        """Control-script commands executed, in order (for inspection)."""
        self._protective_stop_sim_s: float | None = None
        """Controller (simulated) time of the protective stop, None when there is none."""
        self._servers: list[asyncio.Server] = []
        self._connections: dict[asyncio.Task[None], asyncio.StreamWriter] = {}
        self._tick_task: asyncio.Task[None] | None = None
        self._program_task: asyncio.Task[None] | None = None
        self._move_task: asyncio.Task[None] | None = None
        self._start_wall_s = 0.0
        self._last_wall_s = 0.0
        self._snapshot: _Snapshot | None = None
        self._register_offset = 0
        self._async_write_count = 0
        self._async_operation_id = 0

    # --- lifecycle ------------------------------------------------------------------------------

    async def start(self) -> None:
        """Bind the three ports on ``host`` and start the controller's control loop."""
        await self.arm.connect()
        loop = asyncio.get_running_loop()
        self._start_wall_s = self._last_wall_s = loop.time()
        self._snapshot = self._measure(self._start_wall_s, None)
        try:
            for port, handler in (
                (RTDE_PORT, self._serve_rtde),
                (DASHBOARD_PORT, self._serve_dashboard),
                (SCRIPT_PORT, self._serve_script),
            ):
                server = await asyncio.start_server(
                    self._tracked(handler), self.host, port, reuse_address=True
                )
                self._servers.append(server)
        except BaseException:
            await self.close()
            raise
        self._tick_task = asyncio.create_task(self._control_loop(), name="ur-emulator-tick")
        log.info(
            "UR controller emulator on %s (RTDE %d, dashboard %d, script %d)",
            self.host,
            RTDE_PORT,
            DASHBOARD_PORT,
            SCRIPT_PORT,
        )

    async def close(self) -> None:
        """Stop serving, drop every client, stop the arm. Safe to call twice."""
        for server in self._servers:
            server.close()
        # Cancelling a connection task would make asyncio's server log an error: abort the
        # transports instead, so the handlers end on the closed streams.
        connections = list(self._connections.items())
        for _, writer in connections:
            writer.transport.abort()
        tasks = [self._tick_task, self._program_task, self._move_task]
        for task in tasks:
            if task is not None:
                task.cancel()
        await asyncio.gather(
            *(t for t in tasks if t is not None),
            *(t for t, _ in connections),
            return_exceptions=True,
        )
        for server in self._servers:
            await server.wait_closed()
        self._servers.clear()
        self._tick_task = self._program_task = self._move_task = None
        await self.arm.close()

    async def __aenter__(self) -> URControllerEmulator:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    @property
    def protective_stopped(self) -> bool:
        return self._protective_stop_sim_s is not None

    @property
    def program_running(self) -> bool:
        return self.runtime_state == RUNTIME_PLAYING

    def _tracked(
        self, handler: Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]
    ) -> Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]:
        """Wrap a connection handler so close() can drop the connection (the handler then ends
        on the closed stream) and the socket always closes."""

        async def run(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            task = asyncio.current_task()
            assert task is not None
            self._connections[task] = writer
            try:
                await handler(reader, writer)
            except (ConnectionError, asyncio.IncompleteReadError):
                pass  # the client went away; a real controller just drops the session
            finally:
                del self._connections[task]
                writer.close()
                with contextlib.suppress(Exception):
                    await writer.wait_closed()

        return run

    # --- control loop ---------------------------------------------------------------------------

    async def _control_loop(self) -> None:
        """Sample the arm every control period; let idle wall time pass as controller time."""
        loop = asyncio.get_running_loop()
        next_tick = loop.time()
        while True:
            next_tick += self.period_s
            await asyncio.sleep(max(0.0, next_tick - loop.time()))
            now = loop.time()
            if not (await self.arm.state()).is_moving:
                # SimUR5 only advances simulated time while moving; the controller's clock
                # runs on regardless (the protective-stop hold is counted in it).
                self.world.clock.now_s += (
                    now - self._last_wall_s
                ) / self.world.clock.real_time_factor
            self._last_wall_s = now
            self._snapshot = self._measure(now, self._snapshot)

    def _measure(self, wall_s: float, previous: _Snapshot | None) -> _Snapshot:
        joints = self.world.joints_rad.copy()
        pose_tcp = matrix_to_ur_pose(self.world.pose_base_flange @ self._pose_flange_tcp)
        if previous is None or wall_s <= previous.time_s:
            return _Snapshot(wall_s, joints, np.zeros(6), pose_tcp, np.zeros(6))
        dt = wall_s - previous.time_s
        tcp_speed = np.concatenate(
            [
                (pose_tcp[:3] - previous.pose_tcp[:3]) / dt,
                _rotation_rate(previous.pose_tcp, pose_tcp, dt),
            ]
        )
        return _Snapshot(wall_s, joints, (joints - previous.joints) / dt, pose_tcp, tcp_speed)

    # --- RTDE -----------------------------------------------------------------------------------

    async def _serve_rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        outputs: list[tuple[str, str]] = []
        output_frequency_hz = 0.0
        input_recipes: dict[int, list[tuple[str, str]]] = {}
        sender: asyncio.Task[None] | None = None

        def reply(kind: int, payload: bytes = b"") -> None:
            writer.write(struct.pack(">HB", 3 + len(payload), kind) + payload)

        try:
            while True:
                size, kind = struct.unpack(">HB", await reader.readexactly(3))
                payload = await reader.readexactly(size - 3)
                if kind == RTDE_REQUEST_PROTOCOL_VERSION:
                    (version,) = struct.unpack(">H", payload)
                    reply(kind, struct.pack(">B", version == RTDE_PROTOCOL_VERSION))
                elif kind == RTDE_GET_URCONTROL_VERSION:
                    reply(kind, struct.pack(">4I", *CONTROLLER_VERSION))
                elif kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
                    (output_frequency_hz,) = struct.unpack(">d", payload[:8])
                    names = _recipe_names(payload[8:])
                    outputs = [(name, OUTPUT_TYPES.get(name, "NOT_FOUND")) for name in names]
                    types = ",".join(t for _, t in outputs)
                    if "NOT_FOUND" in types:
                        log.warning(
                            "RTDE output variables not served: %s",
                            [n for n, t in outputs if t == "NOT_FOUND"],
                        )
                    reply(kind, struct.pack(">B", 1) + types.encode())
                elif kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
                    names = _recipe_names(payload)
                    recipe = [(name, INPUT_TYPES.get(name, "NOT_FOUND")) for name in names]
                    recipe_id = len(input_recipes) + 1
                    input_recipes[recipe_id] = recipe
                    reply(
                        kind, struct.pack(">B", recipe_id) + ",".join(t for _, t in recipe).encode()
                    )
                elif kind == RTDE_CONTROL_PACKAGE_START:
                    ok = bool(outputs) and all(t != "NOT_FOUND" for _, t in outputs)
                    reply(kind, struct.pack(">B", ok))
                    if ok and sender is None:
                        await writer.drain()
                        sender = asyncio.create_task(
                            self._stream_outputs(writer, outputs, output_frequency_hz),
                            name="ur-emulator-rtde-out",
                        )
                elif kind == RTDE_CONTROL_PACKAGE_PAUSE:
                    if sender is not None:
                        sender.cancel()
                        await asyncio.gather(sender, return_exceptions=True)
                        sender = None
                    reply(kind, struct.pack(">B", 1))
                elif kind == RTDE_DATA_PACKAGE:
                    self._write_inputs(input_recipes.get(payload[0], []), payload[1:])
                elif kind != RTDE_TEXT_MESSAGE:
                    log.warning("RTDE message type %r ignored", chr(kind))
                await writer.drain()
        finally:
            if sender is not None:
                sender.cancel()
                await asyncio.gather(sender, return_exceptions=True)

    async def _stream_outputs(
        self, writer: asyncio.StreamWriter, outputs: list[tuple[str, str]], frequency_hz: float
    ) -> None:
        """Send an output data package (recipe 1) every 1/frequency seconds, drift-free."""
        loop = asyncio.get_running_loop()
        period_s = 1.0 / frequency_hz if frequency_hz > 0 else self.period_s
        formats = ">B" + "".join(RTDE_TYPE_FORMATS[t] for _, t in outputs)
        next_send = loop.time()
        while True:
            # Positions as they are now, speeds from the last control tick.
            assert self._snapshot is not None
            snapshot = dataclasses.replace(
                self._snapshot,
                time_s=loop.time(),
                joints=self.world.joints_rad.copy(),
                pose_tcp=matrix_to_ur_pose(self.world.pose_base_flange @ self._pose_flange_tcp),
            )
            values: list[object] = [1]
            for name, _ in outputs:
                value = self._output_value(name, snapshot)
                values.extend(value if isinstance(value, (list, tuple, np.ndarray)) else [value])
            payload = struct.pack(formats, *values)
            writer.write(struct.pack(">HB", 3 + len(payload), RTDE_DATA_PACKAGE) + payload)
            await writer.drain()
            next_send += period_s
            await asyncio.sleep(max(0.0, next_send - loop.time()))

    def _output_value(self, name: str, snapshot: _Snapshot) -> object:
        match name:
            case "timestamp":
                return snapshot.time_s - self._start_wall_s
            case "actual_q" | "target_q":
                return snapshot.joints
            case "actual_qd" | "target_qd":
                return snapshot.joint_speeds
            case "actual_TCP_pose" | "target_TCP_pose":
                return snapshot.pose_tcp
            case "actual_TCP_speed" | "target_TCP_speed":
                return snapshot.tcp_speed
            case "actual_TCP_force":
                return self.arm.tcp_wrench_base()
            case "tcp_force_scalar":
                return float(np.linalg.norm(self.arm.tcp_wrench_base()[:3]))
            case "robot_mode":
                return ROBOT_MODE_RUNNING
            case "joint_mode":
                return [JOINT_MODE_RUNNING] * 6
            case "safety_mode" | "safety_status":
                return (
                    SAFETY_MODE_PROTECTIVE_STOP if self.protective_stopped else SAFETY_MODE_NORMAL
                )
            case "safety_status_bits":
                return (
                    SAFETY_STATUS_PROTECTIVE_STOPPED
                    if self.protective_stopped
                    else SAFETY_STATUS_NORMAL
                )
            case "runtime_state":
                return self.runtime_state
            case "robot_status_bits":
                return ROBOT_STATUS_POWER_ON | (ROBOT_STATUS_PROGRAM_RUNNING * self.program_running)
            case "speed_scaling" | "target_speed_fraction":
                return 1.0
        if name.startswith("output_int_register_"):
            return self.output_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self.output_double[int(name.rsplit("_", 1)[1])]
        kind = OUTPUT_TYPES[name]
        count = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6}.get(kind)
        return [0] * count if count else 0

    def _write_inputs(self, recipe: list[tuple[str, str]], data: bytes) -> None:
        offset = 0
        for name, kind in recipe:
            code = ">" + RTDE_TYPE_FORMATS.get(kind, "")
            if kind == "NOT_FOUND" or offset + struct.calcsize(code) > len(data):
                log.warning("RTDE input package does not match its recipe at %s", name)
                return
            values = struct.unpack_from(code, data, offset)
            offset += struct.calcsize(code)
            self.inputs[name] = values[0] if len(values) == 1 else values

    # --- dashboard ------------------------------------------------------------------------------

    async def _serve_dashboard(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        writer.write(b"Connected: Universal Robots Dashboard Server\n")
        await writer.drain()
        while line := await reader.readline():
            command = line.decode(errors="replace").strip()
            answer = await self._dashboard_answer(command)
            writer.write(answer.encode() + b"\n")
            await writer.drain()
            if command == "quit":
                return

    async def _dashboard_answer(self, command: str) -> str:
        """The dashboard server's reply to one command (PolyScope 3.15 wording)."""
        version = ".".join(str(v) for v in CONTROLLER_VERSION)
        program = "rtde_control" if self.scripts_received else "<unnamed>"
        state = {RUNTIME_PLAYING: "PLAYING", RUNTIME_PAUSED: "PAUSED"}.get(
            self.runtime_state, "STOPPED"
        )
        safety = "PROTECTIVE_STOP" if self.protective_stopped else "NORMAL"
        match command:
            case "PolyscopeVersion":
                return f"URSoftware {version} (Feb 01 2023)"
            case "robotmode":
                return "Robotmode: RUNNING"
            case "safetymode":
                return f"Safetymode: {safety}"
            case "safetystatus":
                return f"Safetystatus: {safety}"
            case "programState":
                return f"{state} {program}"
            case "running":
                return f"Program running: {str(self.program_running).lower()}"
            case "get robot model":
                return ROBOT_MODEL
            case "get loaded program":
                return "No program loaded"
            case "stop":
                await self._end_program(RUNTIME_STOPPED)
                return "Stopped"
            case "pause":
                if not self.program_running:
                    return "Failed to execute: pause"
                await self._end_program(RUNTIME_PAUSED)
                return "Pausing program"
            case "play":
                return "Failed to execute: play"  # no .urp program is loaded on the emulator
            case "unlock protective stop":
                return await self._unlock_protective_stop()
            case "close safety popup":
                return "closing safety popup"
            case "close popup":
                return "closing popup"
            case "power on":
                return "Powering on"
            case "brake release":
                return "Brake releasing"
            case "quit":
                return "Disconnected"
        return f"could not understand: '{command}'"

    async def _unlock_protective_stop(self) -> str:
        if self._protective_stop_sim_s is None:
            return "Protective stop releasing"
        if self.world.clock.now_s < self._protective_stop_sim_s + PROTECTIVE_STOP_HOLD_S:
            return (
                "Cannot unlock protective stop until 5s after occurrence."
                " Always inspect cause of protective stop before unlocking"
            )
        await self.arm.recover_protective_stop(timeout_s=PROTECTIVE_STOP_HOLD_S)
        self._protective_stop_sim_s = None
        log.info("protective stop unlocked")
        return "Protective stop releasing"

    # --- script port and the control program ----------------------------------------------------

    async def _serve_script(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Collect programs (``def name():`` ... ``end`` at column 0) and run each one."""
        buffer = ""
        while chunk := await reader.read(65536):
            buffer += chunk.decode(errors="replace")
            while match := re.search(r"^end[ \t]*\r?\n", buffer, re.MULTILINE):
                program, buffer = buffer[: match.end()], buffer[match.end() :]
                await self._start_program(program.strip())

    async def _start_program(self, script: str) -> None:
        self.scripts_received.append(script)
        await self._end_program(RUNTIME_STOPPED)
        if CONTROL_SCRIPT_MARKER not in script:
            log.warning("script %r is not ur-rtde's control script; not run", script[:40])
            return
        if self.protective_stopped:
            log.warning("program not started: the robot is in protective stop")
            return
        offset = re.search(r"reg_offset_int\s*=\s*#[^\n]*\n\s*(\d+)", script)
        self._register_offset = int(offset.group(1)) if offset else 0
        self.runtime_state = RUNTIME_PLAYING
        self._program_task = asyncio.create_task(self._run_program(), name="ur-emulator-program")

    async def _end_program(self, runtime_state: int) -> None:
        """Stop the program and any motion it started (program end kills its threads)."""
        current = asyncio.current_task()
        for task in (self._move_task, self._program_task):
            if task is not None and task is not current and not task.done():
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
        self._move_task = None
        if self._program_task is not current:
            self._program_task = None
        self.runtime_state = runtime_state

    async def _run_program(self) -> None:
        """ur-rtde's control-script main loop: one pass per control period."""
        self._signal_async(-1)
        self._write_int(0, SIGNAL_READY)
        executing = False
        keep_running = True
        previous = Command.NONE
        try:
            while keep_running:
                command = int(self._read_int(0))
                if command in REALTIME_COMMANDS:
                    # The real script re-reads a realtime command's setpoint every cycle; none
                    # is emulated, so only its first cycle is recorded (and logged).
                    if command != previous:
                        keep_running = await self._process(command)
                    self._write_int(0, SIGNAL_READY)
                elif command == Command.NONE:
                    executing = False
                    self._write_int(0, SIGNAL_READY)
                elif not executing:
                    keep_running = await self._process(command)
                    executing = True
                previous = command
                await asyncio.sleep(self.period_s)
        except ProtectiveStopError as error:
            self._enter_protective_stop(str(error))
            return
        except MotionRejectedError as error:
            # A UR aborts the program with a runtime error (e.g. no IK solution).
            log.error("control program stopped by a runtime error: %s", error)
        self._program_task = None
        await self._end_program(RUNTIME_STOPPED)

    async def _process(self, command: int) -> bool:
        """Execute one script command; False ends the program (stopScript)."""
        self.commands_received.append(command)
        match command:
            case Command.MOVEJ | Command.MOVEL:
                target = np.array([self._read_double(i) for i in range(6)])
                speed, acceleration = self._read_double(6), self._read_double(7)
                await self._stop_async_move()
                move = self._move(command, target, speed, acceleration)
                if self._read_int(1) == 1:
                    self._signal_async(0)
                    self._move_task = asyncio.create_task(
                        self._move_thread(move), name="ur-emulator-move"
                    )
                else:
                    await move
            case Command.SPEEDL:
                await self._stop_async_move()
                motion = self.arm.follow(
                    self._speed_linear(), MOVE_TIMEOUT_S, timeout_s=2.0 * MOVE_TIMEOUT_S
                )
                self._move_task = asyncio.create_task(
                    self._move_thread(motion), name="ur-emulator-speedl"
                )
            case Command.STOPL | Command.STOPJ | Command.SPEED_STOP:
                # The arm model stops at once; the deceleration (double register 0) is ignored.
                await self._stop_async_move()
            case Command.PROTECTIVE_STOP:
                await self._stop_async_move()
                raise ProtectiveStopError("protective stop triggered by the program")
            case Command.STOP_SCRIPT:
                return False
            case _:
                log.warning(
                    "control-script command %d is not emulated (acknowledged only)", command
                )
        self._write_int(0, SIGNAL_DONE)
        return True

    def _move(
        self, command: int, target: NDArray[np.float64], speed: float, acceleration: float
    ) -> Awaitable[None]:
        if command == Command.MOVEL:
            return self.arm.move_linear(
                target, speed_m_s=speed, acceleration_m_s2=acceleration, timeout_s=MOVE_TIMEOUT_S
            )
        return self.arm.move_joints(
            target, speed_rad_s=speed, acceleration_rad_s2=acceleration, timeout_s=MOVE_TIMEOUT_S
        )

    def _speed_linear(self) -> Callable[[float], NDArray[np.float64]]:
        """speedL as a joint trajectory for ``SimUR5.follow``: the TCP follows the twist in
        double registers 0-5 (base frame; m/s, rad/s), reached at the acceleration in register
        6, until stopped. ur-rtde updates the setpoint by rewriting the registers, so they are
        read at every step (only while the command register still says speedL: a stop command
        reuses register 0). ``follow`` calls the trajectory once per step in time order, which
        lets it integrate the twist step by step."""
        pose_tcp = self.world.pose_base_flange @ self._pose_flange_tcp
        fraction = 0.0  # of the commanded twist reached on the acceleration ramp
        last_time_s = 0.0
        twist, acceleration = np.zeros(6), 1.0

        def joints_at(time_s: float) -> NDArray[np.float64]:
            nonlocal pose_tcp, fraction, last_time_s, twist, acceleration
            dt_s, last_time_s = time_s - last_time_s, time_s
            if self._read_int(0) == Command.SPEEDL:
                twist = np.array([self._read_double(i) for i in range(6)])
                acceleration = self._read_double(6)
            linear, angular = np.linalg.norm(twist[:3]), np.linalg.norm(twist[3:])
            peak = linear if linear > 0.0 else angular
            fraction = min(1.0, fraction + acceleration * dt_s / peak) if peak > 0.0 else 1.0
            step = twist * fraction * dt_s
            pose_tcp = pose_tcp.copy()
            pose_tcp[:3, 3] += step[:3]
            pose_tcp[:3, :3] = Rotation.from_rotvec(step[3:]).as_matrix() @ pose_tcp[:3, :3]
            joints = inverse_kinematics(pose_tcp @ self._pose_tcp_flange, self.world.joints_rad)
            if joints is None:
                raise MotionRejectedError("speedL left the reachable workspace")
            return joints

        return joints_at

    async def _move_thread(self, motion: Awaitable[None]) -> None:
        """An asynchronous motion: report finished in the progress word, or a fault."""
        try:
            await motion
        except ProtectiveStopError as error:
            self._enter_protective_stop(str(error))
            await self._end_program(RUNTIME_PAUSED)
            return
        except MotionRejectedError as error:
            log.error("control program stopped by a runtime error: %s", error)
            await self._end_program(RUNTIME_STOPPED)
            return
        self._move_task = None
        self._signal_async(-1)

    async def _stop_async_move(self) -> None:
        task, self._move_task = self._move_task, None
        if task is not None and not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            self._signal_async(-1)

    def _enter_protective_stop(self, reason: str) -> None:
        log.warning("protective stop: %s", reason)
        self._protective_stop_sim_s = self.world.clock.now_s
        self.runtime_state = RUNTIME_PAUSED

    # --- registers ------------------------------------------------------------------------------

    def _read_int(self, index: int) -> int:
        return int(self.inputs.get(f"input_int_register_{index + self._register_offset}", 0))

    def _read_double(self, index: int) -> float:
        return float(self.inputs.get(f"input_double_register_{index + self._register_offset}", 0.0))

    def _write_int(self, index: int, value: int) -> None:
        self.output_int[index + self._register_offset] = value

    def _signal_async(self, progress: int) -> None:
        """The script's async-progress word: op id (bits 24-30), write count (16-23), running
        (bit 15), progress (0-14). progress 0 starts an operation, < 0 finishes it."""
        self._async_write_count = (self._async_write_count + 1) % 128
        if progress == 0:
            self._async_operation_id = (self._async_operation_id + 1) % 128
        value = self._async_write_count << 16 | self._async_operation_id << 24
        if progress >= 0:
            value |= min(progress, 0x7FFF) | 0x8000
        self._write_int(2, value)


def _recipe_names(payload: bytes) -> list[str]:
    return [name for name in payload.decode().split(",") if name]


def _rotation_rate(
    pose_a: NDArray[np.float64], pose_b: NDArray[np.float64], dt_s: float
) -> NDArray[np.float64]:
    """Angular velocity (base frame, rad/s) turning UR pose a into b in dt_s > 0."""
    relative = Rotation.from_rotvec(pose_b[3:]) * Rotation.from_rotvec(pose_a[3:]).inv()
    return relative.as_rotvec() / dt_s


async def serve_forever(world: SimWorld, config: ArmConfig, *, host: str) -> None:
    """Run an emulator until cancelled (the ``touchshape sim ur-controller`` command)."""
    async with URControllerEmulator(world, config, host=host):
        await asyncio.Event().wait()
