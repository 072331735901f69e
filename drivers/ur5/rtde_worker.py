"""The process that runs the ur-rtde client for ``drivers.ur5.rtde_arm`` (``python -m ...``).

ur-rtde's constructors can block for minutes holding the GIL when the controller accepts a
connection and stays silent, so the client lives here, in its own process, which the driver
kills when a call overruns. The protocol is JSON, one object per line:

- stdin, from the driver: ``{"id": 7, "op": "move_linear", "args": {...}}``.
- the protocol pipe, to the driver: ``{"id": 7, "ok": true, "result": ...}`` or
  ``{"id": 7, "ok": false, "error": "RuntimeError", "message": "..."}``, and after ``connect``
  a state report every ``state_period_s``: ``{"state": {...}}`` (base frame, SI units).

ur-rtde writes its diagnostics to stdout from C++, so the protocol goes to a duplicate of the
original stdout and file descriptor 1 is pointed at stderr. One thread serves requests and
samples the state between them: ur-rtde's interfaces are not shared across threads. When stdin
closes (the driver went away) the arm is stopped and the process exits.
"""

from __future__ import annotations

import json
import os
import select
import sys
import time
from typing import Any, BinaryIO

RECEIVE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "actual_TCP_force",
    "runtime_state",
    "safety_status_bits",
]
"""What the driver needs from RTDE; less than ur-rtde's default recipe (less traffic)."""
RUNTIME_PLAYING = 2
DASHBOARD_TIMEOUT_MS = 2000
SCRIPT_START_TIMEOUT_S = 5.0
STOP_DECELERATION_M_S2 = 2.0
"""stopL deceleration when the driver goes away without saying how."""


class Worker:
    """ur-rtde's three clients (receive, control, dashboard) and the request handlers."""

    def __init__(self, protocol: BinaryIO) -> None:
        self._protocol = protocol
        self.receive: Any = None
        self.control: Any = None
        self.dashboard: Any = None
        self.state_period_s = 0.0

    def send(self, message: dict[str, Any]) -> None:
        self._protocol.write(json.dumps(message).encode() + b"\n")
        self._protocol.flush()

    # --- requests -------------------------------------------------------------------------------

    def connect(self, host: str, frequency_hz: float, state_period_s: float) -> dict[str, Any]:
        """Dashboard first (its connect has a timeout), then RTDE receive and control; the
        control constructor uploads ur-rtde's control script and waits until it runs."""
        import dashboard_client
        import rtde_control
        import rtde_receive

        self.dashboard = dashboard_client.DashboardClient(host)
        self.dashboard.connect(DASHBOARD_TIMEOUT_MS)
        self.receive = rtde_receive.RTDEReceiveInterface(host, frequency_hz, RECEIVE_VARIABLES)
        self.control = rtde_control.RTDEControlInterface(host, frequency_hz)
        self.state_period_s = state_period_s
        return {
            "polyscope_version": self.dashboard.polyscopeVersion(),
            "robot_mode": self.dashboard.robotmode(),
            "safety_status": self.dashboard.safetystatus(),
        }

    def move_linear(self, pose: list[float], speed: float, acceleration: float) -> None:
        """Asynchronous moveL: returns once the control script has started the motion."""
        if not self.control.moveL(pose, speed, acceleration, True):
            raise RuntimeError("the controller did not accept moveL")

    def move_joints(self, joints: list[float], speed: float, acceleration: float) -> None:
        if not self.control.moveJ(joints, speed, acceleration, True):
            raise RuntimeError("the controller did not accept moveJ")

    def stop_linear(self, acceleration: float) -> None:
        """stopL, waiting until the script has processed it."""
        self.control.stopL(acceleration, False)

    def unlock_protective_stop(self) -> dict[str, Any]:
        """The dashboard part of the recovery: unlock, close the safety popup."""
        try:
            self.dashboard.unlockProtectiveStop()
        except RuntimeError as error:  # ur-rtde 1.6 raises when the controller refuses
            return {"unlocked": False, "reply": str(error)}
        self.dashboard.closeSafetyPopup()
        return {"unlocked": True, "reply": str(self.dashboard.safetystatus())}

    def reupload_script(self) -> None:
        """Upload ur-rtde's control script again and wait until the controller runs it
        (reuploadScript itself does not wait)."""
        if not self.control.reuploadScript():
            raise RuntimeError("re-uploading the control script failed")
        deadline_s = time.monotonic() + SCRIPT_START_TIMEOUT_S
        while not self.control.isProgramRunning():
            if time.monotonic() > deadline_s:
                raise RuntimeError(
                    f"control script not running {SCRIPT_START_TIMEOUT_S} s after upload"
                )
            time.sleep(0.01)

    def close(self) -> None:
        """Stop the arm and the control script. The process then exits without ur-rtde's
        disconnect(), which sleeps 0.5 s per interface: the sockets close with the process."""
        if self.control is not None:
            self.control.stopL(STOP_DECELERATION_M_S2, False)
            self.control.stopScript()

    def state(self) -> dict[str, Any]:
        progress = self.control.getAsyncOperationProgressEx()
        return {
            "timestamp_s": self.receive.getTimestamp(),
            "pose": self.receive.getActualTCPPose(),
            "joints": self.receive.getActualQ(),
            "tcp_speed": self.receive.getActualTCPSpeed(),
            "tcp_force": self.receive.getActualTCPForce(),
            "protective_stopped": self.receive.isProtectiveStopped(),
            "emergency_stopped": self.receive.isEmergencyStopped(),
            "program_running": self.receive.getRuntimeState() == RUNTIME_PLAYING,
            "async_running": progress.isAsyncOperationRunning(),
            "async_operation_id": progress.operationId(),
            "connected": self.receive.isConnected() and self.control.isConnected(),
        }

    def handle(self, request: dict[str, Any]) -> bool:
        """Run one request and answer it; False when the worker should exit."""
        op, args = request["op"], request.get("args", {})
        try:
            result = getattr(self, op)(**args) if op in REQUESTS else _unknown(op)
        except Exception as error:  # every failure goes back to the driver, typed by name
            self.send(
                {
                    "id": request["id"],
                    "ok": False,
                    "error": type(error).__name__,
                    "message": str(error),
                }
            )
        else:
            self.send({"id": request["id"], "ok": True, "result": result})
        return op != "close"


REQUESTS = frozenset(
    {
        "connect",
        "move_linear",
        "move_joints",
        "stop_linear",
        "unlock_protective_stop",
        "reupload_script",
        "close",
    }
)


def _unknown(op: str) -> None:
    raise ValueError(f"unknown request {op!r}")


def main() -> None:
    protocol = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    worker = Worker(protocol)
    stdin_fd = sys.stdin.fileno()
    buffer = b""
    next_state_s = time.monotonic()
    running = True
    while running:
        timeout_s = max(0.0, next_state_s - time.monotonic()) if worker.control else None
        readable, _, _ = select.select([stdin_fd], [], [], timeout_s)
        if readable:
            chunk = os.read(stdin_fd, 65536)
            if not chunk:  # the driver is gone: leave the arm stopped
                worker.close()
                break
            buffer += chunk
            while running and b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                running = worker.handle(json.loads(line))
        if worker.control is not None and time.monotonic() >= next_state_s:
            worker.send({"state": worker.state()})
            next_state_s = max(next_state_s + worker.state_period_s, time.monotonic())


if __name__ == "__main__":
    main()
    # Skip the interpreter's shutdown: ur-rtde's destructors disconnect (and sleep).
    os._exit(0)
