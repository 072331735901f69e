"""A real UR5 through ur-rtde, behind the ``Arm`` interface.

The ur-rtde client runs in a worker process (``drivers.ur5.rtde_worker``): its constructors can
block for minutes holding the GIL when a controller accepts the connection and stays silent, so
no thread of this process can call it safely. This module talks to the worker over pipes with
asyncio and never blocks the event loop; a call that overruns kills the worker.

Frames and units: poses are UR poses ``[x, y, z, rx, ry, rz]`` of the controller's TCP in the
robot base frame (metres, axis-angle radians), as ur-rtde reports them; the controller's TCP
must equal ``ArmConfig.tcp_offset`` (``touchshape check arm`` verifies it).

Behaviour:
- ``connect()`` tries ``connect_attempts`` times with exponential backoff, each attempt bounded
  by ``connect_timeout_s``.
- Moves are asynchronous ur-rtde moves (moveL / moveJ with ``asynchronous=True``) whose end is
  read from the control script's async-progress word. ``stop()`` sends stopL and the running
  move returns normally; cancelling the awaiting task sends stopL and re-raises; a protective
  stop raises ``ProtectiveStopError``; ``timeout_s`` stops the arm and raises
  ``DeviceTimeoutError``.
- Limits: speeds and accelerations above the config's limits, non-finite or unreachable targets
  (analytic IK) raise ``MotionRejectedError`` before anything is sent.
- ``recover_protective_stop()`` runs the documented sequence: wait until 5 s after the stop,
  dashboard "unlock protective stop" and "close safety popup", then re-upload the control script.
- Watchdog: no fresh RTDE state (the controller's timestamp must advance) for
  ``watchdog_timeout_s`` while no request is pending, the worker dying, or ur-rtde reporting a
  lost connection mark the link lost: running moves raise ``DeviceConnectionError`` and the
  driver reconnects in the background with exponential backoff until ``close()``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import json
import logging
import math
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.base import (
    Arm,
    ArmState,
    DeviceConnectionError,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    MotionRejectedError,
    ProtectiveStopError,
)
from drivers.config import ArmConfig
from drivers.ur5.kinematics import inverse_kinematics
from models.geometry import invert_transform, ur_pose_to_matrix

log = logging.getLogger(__name__)

WORKER_COMMAND = (sys.executable, "-m", "drivers.ur5.rtde_worker")

CLOSED = "closed by the driver"
PROTECTIVE_STOP_HOLD_S = 5.0
"""A UR refuses to unlock a protective stop earlier than this after it happened."""
JOINT_LIMIT_RAD = 2.0 * math.pi
REQUEST_TIMEOUT_S = 5.0
"""A request to the worker other than connect (ur-rtde waits up to 3 s for the script)."""
RECOVERY_REQUEST_TIMEOUT_S = 10.0
"""Re-uploading the control script waits up to 5 s for it to run."""
CLOSE_TIMEOUT_S = 5.0
STOP_DECELERATION_M_S2 = 2.0
"""stopL deceleration of stop(), cancellation and timeouts."""
BACKOFF_INITIAL_S = 0.5
BACKOFF_MAX_S = 8.0
STATE_PERIOD_S = 0.01
"""How often the worker reports the state (100 Hz; the RTDE stream itself runs at 125 Hz)."""
UNLOCK_RETRY_S = 0.5


@dataclass(frozen=True)
class RtdeState:
    """One state report of the worker (base frame, SI units)."""

    timestamp_s: float
    """Controller time."""
    pose: NDArray[np.float64]
    joints: NDArray[np.float64]
    tcp_speed: NDArray[np.float64]
    tcp_force: NDArray[np.float64]
    """getActualTCPForce: force (N) and torque (N m) at the TCP, base frame."""
    protective_stopped: bool
    emergency_stopped: bool
    program_running: bool
    """ur-rtde's control script runs on the controller."""
    async_running: bool
    async_operation_id: int
    connected: bool

    @classmethod
    def from_message(cls, message: dict[str, Any]) -> RtdeState:
        arrays = {
            k: np.asarray(message[k], dtype=float)
            for k in ("pose", "joints", "tcp_speed", "tcp_force")
        }
        return cls(**{**message, **arrays})

    @property
    def is_moving(self) -> bool:
        """The TCP moves (0.1 mm/s, 1 mrad/s) or an asynchronous move is under way."""
        if self.protective_stopped:
            return False
        turning = np.linalg.norm(self.tcp_speed[3:]) > 1e-3
        return bool(np.linalg.norm(self.tcp_speed[:3]) > 1e-4 or turning or self.async_running)


class WorkerLink:
    """One worker process: requests with timeouts, the state stream, and the link watchdog.

    ``lost`` is set (with a reason) once the link is unusable; the worker is then killed.
    """

    def __init__(
        self,
        process: subprocess.Popen[bytes],
        stdin: asyncio.WriteTransport,
        stdout: asyncio.StreamReader,
        stderr: asyncio.StreamReader,
        watchdog_timeout_s: float,
    ) -> None:
        self.process = process
        self._stdin, self._stdout, self._stderr = stdin, stdout, stderr
        self._watchdog_timeout_s = watchdog_timeout_s
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._state_waiters: list[asyncio.Future[RtdeState]] = []
        self.state: RtdeState | None = None
        self.state_time_s = 0.0
        """Event-loop time of the last state whose controller timestamp advanced."""
        self.protective_stop_since_s: float | None = None
        """Event-loop time the current protective stop was first reported."""
        self._diagnostics: collections.deque[str] = collections.deque(maxlen=3)
        self.lost: str | None = None
        self.lost_event = asyncio.Event()
        self._tasks = [
            asyncio.create_task(self._read_protocol(), name="ur-rtde-protocol"),
            asyncio.create_task(self._read_diagnostics(), name="ur-rtde-stderr"),
            asyncio.create_task(self._watchdog(), name="ur-rtde-watchdog"),
        ]

    @classmethod
    async def spawn(
        cls, watchdog_timeout_s: float, command: Sequence[str] = WORKER_COMMAND
    ) -> WorkerLink:
        """Start the worker. Popen runs in a thread: it returns only once the child has
        exec'd (milliseconds, tens of them on a loaded machine), too long for the loop."""
        pipe = subprocess.PIPE
        process = await asyncio.to_thread(
            subprocess.Popen, list(command), stdin=pipe, stdout=pipe, stderr=pipe
        )
        loop = asyncio.get_running_loop()
        try:
            stdin, _ = await loop.connect_write_pipe(asyncio.Protocol, process.stdin)
            stdout, stderr = asyncio.StreamReader(), asyncio.StreamReader()
            for reader, pipe_file in ((stdout, process.stdout), (stderr, process.stderr)):
                await loop.connect_read_pipe(
                    lambda reader=reader: asyncio.StreamReaderProtocol(reader), pipe_file
                )
        except BaseException:
            process.kill()
            await asyncio.to_thread(process.wait)
            raise
        return cls(process, stdin, stdout, stderr, watchdog_timeout_s)

    async def request(self, op: str, timeout_s: float, **args: Any) -> Any:
        """Send one request; a worker that does not answer in time is killed."""
        if self.lost is not None:
            raise DeviceConnectionError(f"UR link lost: {self.lost}")
        request_id = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future
        self._stdin.write(json.dumps({"id": request_id, "op": op, "args": args}).encode() + b"\n")
        try:
            async with asyncio.timeout(timeout_s):
                return await future
        except TimeoutError:
            await self.fail(f"{op} did not finish within {timeout_s} s")
            raise DeviceTimeoutError(f"UR {op} did not finish within {timeout_s} s") from None
        finally:
            self._pending.pop(request_id, None)

    async def next_state(self) -> RtdeState:
        """The next state report; DeviceConnectionError when the link is lost first."""
        if self.lost is not None:
            raise DeviceConnectionError(f"UR link lost: {self.lost}")
        future: asyncio.Future[RtdeState] = asyncio.get_running_loop().create_future()
        self._state_waiters.append(future)
        try:
            return await future
        finally:
            with contextlib.suppress(ValueError):
                self._state_waiters.remove(future)

    async def fail(self, reason: str) -> None:
        """Mark the link lost, fail everything waiting on it and kill the worker."""
        if self.lost is None:
            self.lost = reason
            self.lost_event.set()
            error = DeviceConnectionError(f"UR link lost: {reason}")
            for future in [*self._pending.values(), *self._state_waiters]:
                if not future.done():
                    future.set_exception(error)
        await self.kill()

    async def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            await asyncio.to_thread(self.process.wait)
        self._stdin.close()
        current = asyncio.current_task()
        for task in self._tasks:
            if task is not current:
                task.cancel()

    async def _read_protocol(self) -> None:
        while line := await self._stdout.readline():
            try:
                message = json.loads(line)
            except ValueError:
                await self.fail(f"unreadable message from the worker: {line[:80]!r}")
                return
            if "state" in message:
                self._on_state(RtdeState.from_message(message["state"]))
            elif (future := self._pending.get(message["id"])) is not None and not future.done():
                if message["ok"]:
                    future.set_result(message["result"])
                else:
                    future.set_exception(_WorkerError(f"{message['error']}: {message['message']}"))
        code = await asyncio.to_thread(self.process.wait)
        await asyncio.sleep(0.05)  # let the last diagnostics arrive
        await self.fail(f"worker exited (code {code}): {' | '.join(self._diagnostics)}")

    def _on_state(self, state: RtdeState) -> None:
        now_s = asyncio.get_running_loop().time()
        if self.state is None or state.timestamp_s != self.state.timestamp_s:
            self.state_time_s = now_s
        if not state.protective_stopped:
            self.protective_stop_since_s = None
        elif self.protective_stop_since_s is None:
            self.protective_stop_since_s = now_s
        self.state = state
        waiters, self._state_waiters = self._state_waiters, []
        for future in waiters:
            if not future.done():
                future.set_result(state)
        if not state.connected and self.lost is None:
            self._tasks.append(asyncio.create_task(self.fail("ur-rtde lost the controller")))

    async def _read_diagnostics(self) -> None:
        while line := await self._stderr.readline():
            text = line.decode(errors="replace").rstrip()
            self._diagnostics.append(text)
            log.debug("ur-rtde: %s", text)

    async def _watchdog(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(self._watchdog_timeout_s / 4)
            stale_s = loop.time() - self.state_time_s
            if self.state is not None and not self._pending and stale_s > self._watchdog_timeout_s:
                await self.fail(f"no fresh RTDE state for {stale_s:.2f} s (watchdog)")
                return


class _WorkerError(DeviceError):
    """A ur-rtde call raised in the worker."""


class URRtdeArm(Arm):
    """A UR5 (or any UR) through ur-rtde; see the module docstring for behaviour."""

    def __init__(self, config: ArmConfig) -> None:
        self._config = config
        self._pose_tcp_flange = invert_transform(ur_pose_to_matrix(config.tcp_offset))
        self._link: WorkerLink | None = None
        self._wanted = False
        """connect() succeeded and close() was not called: a lost link is re-opened."""
        self._reconnect_task: asyncio.Task[None] | None = None
        self._supervisor_task: asyncio.Task[None] | None = None
        self._moving = False
        self._stop_requested = False
        self.controller_info: dict[str, str] = {}
        """PolyScope version, robot mode and safety status read at the last connection."""

    # --- lifecycle ------------------------------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        return self._link is not None and self._link.lost is None

    async def connect(self) -> None:
        """Open the link, retrying with backoff; DeviceConnectionError after the last attempt."""
        if self.is_connected:
            return
        if self._reconnect_task is not None:
            self._reconnect_task.cancel()
            await asyncio.gather(self._reconnect_task, return_exceptions=True)
        await self._open_with_backoff(self._config.connect_attempts)
        self._wanted = True

    async def close(self) -> None:
        """Stop the arm and the control script, disconnect, end the worker. Idempotent."""
        self._wanted = False
        for task in (self._reconnect_task, self._supervisor_task):
            if task is not None and task is not asyncio.current_task():
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
        self._reconnect_task = self._supervisor_task = None
        link, self._link = self._link, None
        if link is None:
            return
        if link.lost is None:
            with contextlib.suppress(DeviceError):
                await link.request("close", CLOSE_TIMEOUT_S)
        await link.fail(CLOSED)

    async def _open_with_backoff(self, attempts: int | None) -> None:
        """Open a link; ``attempts`` None retries until cancelled."""
        delay_s = BACKOFF_INITIAL_S
        for attempt in itertools.count(1):
            try:
                await self._open()
                return
            except DeviceError as error:
                if attempts is not None and attempt >= attempts:
                    raise DeviceConnectionError(
                        f"UR controller at {self._config.host} unreachable after {attempt}"
                        f" attempts: {error}"
                    ) from error
                log.warning(
                    "UR connection attempt %d failed (%s); retry in %.1f s", attempt, error, delay_s
                )
            await asyncio.sleep(delay_s)
            delay_s = min(2.0 * delay_s, BACKOFF_MAX_S)

    async def _open(self) -> None:
        link = await WorkerLink.spawn(self._config.watchdog_timeout_s)
        try:
            self.controller_info = await link.request(
                "connect",
                self._config.connect_timeout_s,
                host=self._config.host,
                frequency_hz=self._config.control_frequency_hz,
                state_period_s=STATE_PERIOD_S,
            )
            await link.next_state()
        except BaseException:
            await link.kill()
            raise
        self._link = link
        self._supervisor_task = asyncio.create_task(
            self._supervise(link), name="ur-rtde-supervisor"
        )
        log.info("UR controller at %s: %s", self._config.host, self.controller_info)

    async def _supervise(self, link: WorkerLink) -> None:
        """Start reconnecting when this link is lost while the arm is wanted."""
        await link.lost_event.wait()
        if link is not self._link or not self._wanted:
            return
        log.error("UR link lost (%s); reconnecting", link.lost)
        self._reconnect_task = asyncio.create_task(
            self._open_with_backoff(None), name="ur-rtde-reconnect"
        )

    # --- state ----------------------------------------------------------------------------------

    def _require_link(self) -> WorkerLink:
        if self._link is None:
            raise DeviceNotConnectedError("UR arm is not connected")
        if self._link.lost is not None:
            raise DeviceConnectionError(f"UR link lost ({self._link.lost}); reconnecting")
        return self._link

    @staticmethod
    def _latest(link: WorkerLink) -> RtdeState:
        assert link.state is not None  # a link is kept only after its first state
        return link.state

    async def state(self) -> ArmState:
        link = self._require_link()
        state = self._latest(link)
        return ArmState(
            pose_base_tcp=state.pose.copy(),
            joints_rad=state.joints.copy(),
            is_moving=self._moving or state.is_moving,
            protective_stopped=state.protective_stopped,
            timestamp_s=state.timestamp_s,
            tcp_wrench_base=state.tcp_force.copy(),
        )

    # --- motion ---------------------------------------------------------------------------------

    async def move_linear(
        self,
        pose_base_tcp: NDArray[np.float64],
        *,
        speed_m_s: float,
        acceleration_m_s2: float,
        timeout_s: float,
    ) -> None:
        """moveL to a UR pose of the TCP in the base frame."""
        target = _finite_vector("pose_base_tcp", pose_base_tcp)
        check_limit("speed_m_s", speed_m_s, self._config.max_tool_speed_m_s)
        check_limit("acceleration_m_s2", acceleration_m_s2, self._config.max_tool_acceleration_m_s2)
        link = self._require_link()
        pose_base_flange = ur_pose_to_matrix(target) @ self._pose_tcp_flange
        if inverse_kinematics(pose_base_flange, self._latest(link).joints) is None:
            raise MotionRejectedError(f"pose {target} is unreachable for a UR5")
        await self._move(
            link,
            "move_linear",
            pose=target.tolist(),
            speed=speed_m_s,
            acceleration=acceleration_m_s2,
            timeout_s=timeout_s,
        )

    async def move_joints(
        self,
        joints_rad: NDArray[np.float64],
        *,
        speed_rad_s: float,
        acceleration_rad_s2: float,
        timeout_s: float,
    ) -> None:
        """moveJ to joint angles (rad), all joints arriving together."""
        target = _finite_vector("joints_rad", joints_rad)
        if np.any(np.abs(target) > JOINT_LIMIT_RAD):
            raise MotionRejectedError(f"joints_rad exceed the joint limits +-2 pi: {target}")
        check_limit("speed_rad_s", speed_rad_s, self._config.max_joint_speed_rad_s)
        check_limit(
            "acceleration_rad_s2", acceleration_rad_s2, self._config.max_joint_acceleration_rad_s2
        )
        link = self._require_link()
        await self._move(
            link,
            "move_joints",
            joints=target.tolist(),
            speed=speed_rad_s,
            acceleration=acceleration_rad_s2,
            timeout_s=timeout_s,
        )

    async def _move(self, link: WorkerLink, op: str, *, timeout_s: float, **args: Any) -> None:
        if not timeout_s > 0.0:
            raise MotionRejectedError(f"timeout_s must be positive, got {timeout_s}")
        if self._moving:
            raise MotionRejectedError("busy: the arm is already moving")
        state = self._latest(link)
        if state.protective_stopped:
            raise ProtectiveStopError("in protective stop: call recover_protective_stop() first")
        self._moving = True
        self._stop_requested = False
        try:
            async with asyncio.timeout(timeout_s):
                if not state.program_running:
                    # A runtime error or a dashboard "stop" ended ur-rtde's control script.
                    log.warning("UR control script not running; re-uploading it")
                    await link.request("reupload_script", RECOVERY_REQUEST_TIMEOUT_S)
                operation_before = self._latest(link).async_operation_id
                try:
                    await link.request(op, REQUEST_TIMEOUT_S, **args)
                except _WorkerError as error:
                    if self._latest(link).protective_stopped:
                        raise ProtectiveStopError(f"UR in protective stop: {error}") from error
                    raise MotionRejectedError(f"UR refused {op}: {error}") from error
                await self._wait_for_move_end(link, operation_before)
        except TimeoutError:
            await self._stop_quietly(link)
            raise DeviceTimeoutError(f"UR {op} did not finish within {timeout_s} s") from None
        except asyncio.CancelledError:
            await asyncio.shield(self._stop_quietly(link))
            raise
        except DeviceConnectionError as error:
            if link.lost == CLOSED:
                raise DeviceNotConnectedError("UR arm closed during a move") from error
            raise
        finally:
            self._moving = False

    async def _wait_for_move_end(self, link: WorkerLink, operation_before: int) -> None:
        while True:
            state = await link.next_state()
            if state.protective_stopped:
                raise ProtectiveStopError("UR protective stop during the move")
            if state.emergency_stopped:
                raise DeviceError("UR emergency stop during the move")
            if self._stop_requested:
                return
            if not state.program_running:
                raise DeviceError("the UR control script stopped during the move (runtime error)")
            if state.async_operation_id != operation_before and not state.async_running:
                return

    async def stop(self) -> None:
        """stopL now; a running move then returns normally. A no-op when not connected."""
        if self.is_connected:
            assert self._link is not None
            await self._link.request(
                "stop_linear", REQUEST_TIMEOUT_S, acceleration=STOP_DECELERATION_M_S2
            )
            self._stop_requested = True

    async def _stop_quietly(self, link: WorkerLink) -> None:
        """stopL after a timeout or a cancellation; a failure is logged, the link has its own
        fault handling."""
        try:
            await link.request(
                "stop_linear", REQUEST_TIMEOUT_S, acceleration=STOP_DECELERATION_M_S2
            )
        except DeviceError as error:
            log.error("stopL failed: %s", error)

    # --- protective stop ------------------------------------------------------------------------

    async def recover_protective_stop(self, *, timeout_s: float = 30.0) -> None:
        """Wait until 5 s after the stop, unlock it on the dashboard, close the safety popup
        and re-upload the control script (ur-rtde's documented sequence)."""
        link = self._require_link()
        loop = asyncio.get_running_loop()
        try:
            async with asyncio.timeout(timeout_s):
                if not self._latest(link).protective_stopped:
                    return
                assert link.protective_stop_since_s is not None
                await asyncio.sleep(
                    link.protective_stop_since_s + PROTECTIVE_STOP_HOLD_S - loop.time()
                )
                while True:
                    answer = await link.request("unlock_protective_stop", REQUEST_TIMEOUT_S)
                    if answer["unlocked"]:
                        break
                    log.info("UR refused the unlock (%s); retrying", answer["reply"])
                    await asyncio.sleep(UNLOCK_RETRY_S)
                while self._latest(link).protective_stopped:
                    await link.next_state()
                await link.request("reupload_script", RECOVERY_REQUEST_TIMEOUT_S)
        except TimeoutError:
            raise DeviceTimeoutError(
                f"protective stop not recovered within {timeout_s} s"
                f" (a UR unlocks it {PROTECTIVE_STOP_HOLD_S} s after it happened at the earliest)"
            ) from None
        log.info("UR protective stop recovered")


def check_limit(name: str, value: float, maximum: float) -> None:
    """MotionRejectedError unless 0 < value <= maximum (also for NaN)."""
    if not 0.0 < value <= maximum:
        raise MotionRejectedError(f"{name} must be in (0, {maximum}], got {value}")


def _finite_vector(name: str, values: NDArray[np.float64]) -> NDArray[np.float64]:
    vector = np.asarray(values, dtype=float)
    if vector.shape != (6,) or not np.all(np.isfinite(vector)):
        raise MotionRejectedError(f"{name} must be 6 finite values, got {vector}")
    return vector
