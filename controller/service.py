"""The long-running service: devices, the Zenoh API and one exploration session at a time.

``TouchshapeService.serve`` opens the Zenoh session (a bad endpoint fails before any device
moves), connects the devices, declares the API and serves until its stop event is set
(``touchshape serve`` sets it on SIGINT/SIGTERM); then it aborts a running session (stopping all
motion), closes Zenoh and the devices, and returns.
"""

from __future__ import annotations

import asyncio
import base64
import logging
import time
import uuid
import zlib
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from controller.config import Config
from controller.messaging import ServiceApi, open_session
from controller.motion.safety import Obstacles
from controller.perception.protocol import Perception, ShapeEstimate
from controller.recording import SessionRecorder
from controller.recording_recovery import recover_interrupted_sessions
from controller.request import ExploreRequest, RequestError, parse_explore_request
from controller.scoring import object_size_cm
from controller.session import ExplorationSession
from controller.session_files import (
    SESSION_LOG_FILE,
    attach_session_log,
    detach_session_log,
    save_artifacts,
    save_config,
    save_truth,
)
from controller.states import State
from drivers.factory import Devices, make_devices

log = logging.getLogger(__name__)

PerceptionFactory = Callable[[Config, Devices], Perception]


def encode_shape(session_id: str, touch: int, estimate: ShapeEstimate) -> dict[str, Any]:
    """The ``shape`` publication (docs/api.md): occupancy probabilities quantised to uint8
    (v * 255), C order [i][j][k], zlib-compressed and base64-encoded, with the 4x4 affine that
    maps continuous voxel coordinates to world metres."""
    quantised = np.clip(np.round(estimate.probabilities * 255), 0, 255).astype(np.uint8)
    return {
        "session": session_id,
        "touch": touch,
        "resolution": int(quantised.shape[0]),
        "matrix_world_voxel": estimate.grid.matrix_world_voxel.tolist(),
        "encoding": "uint8-probability-x255/C-order-ijk/zlib/base64",
        "data": base64.b64encode(zlib.compress(quantised.tobytes(), 6)).decode("ascii"),
    }


def decode_shape(message: dict[str, Any]) -> np.ndarray:
    """Probabilities (float32, N^3) from a ``shape`` publication."""
    resolution = message["resolution"]
    raw = zlib.decompress(base64.b64decode(message["data"]))
    quantised = np.frombuffer(raw, dtype=np.uint8).reshape((resolution,) * 3)
    return quantised.astype(np.float32) / 255.0


class TouchshapeService:
    """Owns the devices and at most one running session."""

    def __init__(
        self,
        config: Config,
        perception_factory: PerceptionFactory,
        *,
        logs_dir: Path | None = None,
        rng_seed: int = 0,
        on_publish: Callable[[str, dict[str, Any]], None] | None = None,
    ) -> None:
        """``on_publish(name, body)`` sees every publication, with or without Zenoh (from the
        event loop or a worker thread): ``touchshape explore`` prints its progress from them."""
        self.config = config
        self.on_publish = on_publish
        self.perception_factory = perception_factory
        self.logs_dir = Path(logs_dir or config.logging.dir)
        self.rng_seed = rng_seed
        self.devices: Devices | None = None
        self.perception: Perception | None = None
        self.api: ServiceApi | None = None
        self.session: ExplorationSession | None = None
        self._session_task: asyncio.Task[dict[str, Any]] | None = None
        self._abort = asyncio.Event()
        self.results: list[dict[str, Any]] = []
        self._last_done = False
        """Whether the last session ended done; if not (a fault, an abort, or none yet), the
        arm is wherever that left it, and the next session starts by going home."""
        self._last_obstacles = Obstacles.none()
        """Where the last session found the object may be: the next way home keeps clear of it
        (the object is assumed to stay between sessions)."""
        self.defaults = ExploreRequest(prior=config.models.prior, update=config.models.update)
        self.prior_names: frozenset[str] = frozenset()
        """What requests may name as ``prior`` (the perception's, read at start)."""

    # --- lifecycle ------------------------------------------------------------------------------

    async def start(self) -> None:
        """Connect and home the devices and build the perception (no Zenoh)."""
        config = self.config
        # Before any session starts: sessions a crash ended get their summary (interrupted).
        await asyncio.to_thread(recover_interrupted_sessions, self.logs_dir)
        log.info(
            "connecting the devices: arm %s, gripper %s, sensor %s, camera %s",
            config.robot.arm.type,
            config.gripper.type,
            config.sensor.type,
            config.cameras.rgbd.type,
        )
        # Building the simulated world (mesh, scene, gel model) takes a while: off the loop.
        self.devices = await asyncio.to_thread(
            make_devices,
            arm=config.robot.arm,
            gripper=config.gripper,
            sensor=config.sensor,
            camera=config.cameras.rgbd,
            sim=config.sim,
            rng=np.random.default_rng(self.rng_seed),
            max_object_extent_m=config.voxel_grid.extent_m,
        )
        await self.devices.connect()
        log.info("homing the gripper")
        await self.devices.gripper.home()
        self.perception = await asyncio.to_thread(self.perception_factory, config, self.devices)
        self.prior_names = await asyncio.to_thread(self.perception.prior_names)

    async def stop(self) -> None:
        await self.abort_session()
        if self.devices is not None:
            await self.devices.close()
            self.devices = None

    async def serve(
        self,
        stop: asyncio.Event,
        ready: asyncio.Event | None = None,
        session: zenoh.Session | None = None,
    ) -> None:
        """Serve the Zenoh API until ``stop`` is set. The Zenoh session is opened (or given, and
        then owned and closed here) before the devices connect: a taken port or a bad endpoint
        fails fast (``EndpointError``) with the arm and gripper untouched."""
        if session is None:
            session = await asyncio.to_thread(open_session, self.config.messaging)
        loop = asyncio.get_running_loop()
        try:
            await self.start()
            self.api = ServiceApi(
                session,
                self.config.robot.id,
                loop,
                {"explore": self._on_explore, "abort": self._on_abort, "status": self._on_status},
            )
            self._publish("state", self._state_message(State.IDLE, None))
            if ready is not None:
                ready.set()
            await stop.wait()
        finally:
            await self.stop()
            if self.api is not None:
                await self.api.close()
                self.api = None
            await asyncio.to_thread(session.close)

    # --- sessions -------------------------------------------------------------------------------

    def start_session(self, request: ExploreRequest) -> str:
        """Start a session in the background; RuntimeError when one is running."""
        if self.busy:
            assert self.session is not None
            raise RuntimeError(f"busy: session {self.session.session_id} is running")
        assert self.devices is not None and self.perception is not None
        started = time.time()
        session_id = time.strftime("%Y%m%d-%H%M%S-", time.localtime(started)) + uuid.uuid4().hex[:6]
        self.logs_dir.mkdir(parents=True, exist_ok=True)
        recorder = SessionRecorder(self.logs_dir, session_id, request.__dict__)
        session_log = attach_session_log(recorder.artifacts_dir / SESSION_LOG_FILE)
        world = self.devices.world
        session = ExplorationSession(
            session_id=session_id,
            request=request,
            config=self.config,
            devices=self.devices,
            perception=self.perception,
            recorder=recorder,
            publish=self._publish,
            publish_shape=lambda estimate: self._publish(
                "shape", encode_shape(session_id, session.touch_count, estimate)
            ),
            home_clear_of=None if self._last_done else self._last_obstacles,
        )
        camera_position = self.config.cameras.rgbd.pose_world_camera()[:3, 3]
        grid = self.config.voxel_grid.grid(tuple(camera_position))
        recorder.log_setup(
            session.pose_world_base, grid, world.object_mesh_world if world is not None else None
        )
        self.session = session
        self._abort = asyncio.Event()
        self._session_task = asyncio.create_task(
            self._run_session(session, recorder, session_log, started),
            name=f"session-{session_id}",
        )
        return session_id

    async def _run_session(
        self,
        session: ExplorationSession,
        recorder: SessionRecorder,
        session_log: logging.Handler,
        started: float,
    ) -> dict[str, Any]:
        try:
            try:
                await asyncio.to_thread(self._save_inputs, recorder.artifacts_dir)
                summary = await session.run(self._abort)
                summary["started"] = _iso_time(started)
                world = self.devices.world if self.devices is not None else None
                if world is not None:
                    summary["object"] = self.config.sim.object
                vision = session.vision_estimate
                if vision is not None:
                    # What the session started from: an ``auto`` request resolved.
                    summary["vision"] = {"input": vision.input, "prior": vision.prior}
                summary["object_size_cm"] = object_size_cm(
                    session.vision_estimate,
                    session.estimate,
                    world.object_mesh_world if world is not None else None,
                )
                self._last_done = summary["state"] == str(State.DONE)
                if session.estimate is not None or session.bound is not None:
                    self._last_obstacles = session.obstacles()
                # Compressing the voxels, meshing and writing them, and flushing the recording
                # take tens of milliseconds or more: worker threads' time, not the event loop's.
                summary["artifacts"] = await asyncio.to_thread(
                    self._save_artifacts, session, recorder
                )
            finally:
                await asyncio.to_thread(recorder.close)
            saved = await asyncio.to_thread(recorder.save_summary, summary)
            summary["artifacts"]["summary"] = str(saved)
            session.finish()
            self.results.append(summary)
            self._publish("result", summary)
            return summary
        finally:
            detach_session_log(session_log)

    def _save_inputs(self, folder: Path) -> None:
        """What a replay needs besides the sensors' data: the effective config and, on the
        simulated bench, the true object. A failed write costs the replay, not the session."""
        world = self.devices.world if self.devices is not None else None
        try:
            save_config(folder, self.config)
            if world is not None:
                save_truth(folder, world.object_mesh_world)
        except OSError as error:
            log.error("%s: the session's config or truth could not be saved: %s", folder, error)

    def _save_artifacts(
        self, session: ExplorationSession, recorder: SessionRecorder
    ) -> dict[str, str]:
        world = self.devices.world if self.devices is not None else None
        return save_artifacts(
            recorder,
            session.estimate,
            session.vision_estimate,
            session.outcomes,
            session.outcome_touches,
            session.touch_count,
            world.object_mesh_world if world is not None else None,
        )

    async def wait_session(self) -> dict[str, Any] | None:
        if self._session_task is None:
            return None
        return await self._session_task

    async def abort_session(self) -> bool:
        if not self.busy:
            return False
        self._abort.set()
        await asyncio.gather(self._session_task, return_exceptions=True)  # type: ignore[arg-type]
        return True

    @property
    def busy(self) -> bool:
        return self._session_task is not None and not self._session_task.done()

    # --- Zenoh handlers -------------------------------------------------------------------------

    async def _on_explore(self, payload: bytes) -> dict[str, Any]:
        try:
            request = parse_explore_request(payload, self.defaults, priors=self.prior_names)
            session_id = self.start_session(request)
        except (RequestError, RuntimeError, ValueError) as error:
            return {"accepted": False, "error": str(error)}
        return {"accepted": True, "session": session_id}

    async def _on_abort(self, payload: bytes) -> dict[str, Any]:
        if not self.busy:  # the last session, finished, is not what was aborted
            return {"aborted": False, "session": None}
        assert self.session is not None
        session_id = self.session.session_id
        return {"aborted": await self.abort_session(), "session": session_id}

    async def _on_status(self, payload: bytes) -> dict[str, Any]:
        session = self.session
        return {
            "state": str(session.state) if session is not None else str(State.IDLE),
            "session": session.session_id if session is not None else None,
            "touch": session.touch_count if session is not None else 0,
            "busy": self.busy,
            "sessions_completed": len(self.results),
        }

    def _state_message(self, state: State, session_id: str | None) -> dict[str, Any]:
        return {
            "session": session_id,
            "state": str(state),
            "previous": None,
            "touch": 0,
            "time": time.time(),
        }

    def _publish(self, name: str, body: dict[str, Any]) -> None:
        if self.on_publish is not None:
            self.on_publish(name, body)
        if self.api is not None:
            self.api.publish_json(name, body)


def _iso_time(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, tz=UTC).isoformat(timespec="seconds")
