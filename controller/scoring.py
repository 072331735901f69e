"""Scores of a session's shape estimates. Ground truth: only a simulated bench knows the true
shape, so a session scores only when the devices share a ``SimWorld`` (a real robot's session
has none and gets no scores, rather than scores against an object that is not there). The
object's size is reported on every bench, with the truth's where it is known."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from controller.perception.protocol import ShapeEstimate
from controller.recording import SessionRecorder
from models.geometry import extent_along_axes_m, occupied_extent_m
from models.metrics import surfaces_metrics

if TYPE_CHECKING:
    from drivers.sim.world import SimWorld

log = logging.getLogger(__name__)

SCORES = ("chamfer_mm", "fscore_2mm", "fscore_5mm")
"""Ground-truth scores of every estimate on the simulated bench (``models.metrics``)."""


class GroundTruthScores:
    """Scores every estimate against the simulated object in the background (no work a real
    robot would wait for); ``collect`` lists them in estimate order."""

    def __init__(
        self,
        world: SimWorld,
        recorder: SessionRecorder,
        on_score: Callable[[int, dict[str, float]], None] = lambda touch, scores: None,
    ) -> None:
        """``on_score(touch, scores)`` is called on the event loop as each score is ready."""
        self.world = world
        self.recorder = recorder
        self.on_score = on_score
        self._tasks: list[asyncio.Task[dict[str, float]]] = []

    @classmethod
    def published(
        cls,
        world: SimWorld,
        recorder: SessionRecorder,
        publish: Callable[[str, dict], None],
        session_id: str,
    ) -> GroundTruthScores:
        """Scores published on the session's ``score`` topic as they are ready."""

        def on_score(touch: int, scores: dict[str, float]) -> None:
            publish("score", {"session": session_id, "touch": touch, **scores})

        return cls(world, recorder, on_score)

    def add(self, estimate: ShapeEstimate, touch: int) -> None:
        mesh = self.world.object_mesh_world
        self._tasks.append(asyncio.create_task(self._score(estimate, mesh, touch)))

    async def _score(
        self, estimate: ShapeEstimate, mesh: trimesh.Trimesh, touch: int
    ) -> dict[str, float]:
        values = await asyncio.to_thread(score_estimate, estimate, mesh)
        for name, value in values.items():
            self.recorder.log_metric(name, value, touch=touch)
        try:
            self.on_score(touch, values)
        except Exception:  # a listener's failure must not lose the score
            log.exception("publishing the score of touch %d failed", touch)
        return values

    async def collect(self) -> dict[str, list[float]]:
        """Wait for the scores; one list per score name, in estimate order."""
        results = await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        metrics: dict[str, list[float]] = {}
        for result in results:
            if isinstance(result, BaseException):
                log.error("scoring an estimate failed: %r", result)
                continue
            for name, value in result.items():
                metrics.setdefault(name, []).append(round(value, 3))
        return metrics


def score_estimate(estimate: ShapeEstimate, true_mesh_world: trimesh.Trimesh) -> dict[str, float]:
    """``SCORES`` of the estimate's surface (``ShapeEstimate.surface_mesh``: every update
    through the same extraction) against the truth."""
    scores = surfaces_metrics(estimate.surface_mesh(), true_mesh_world)
    return {name: float(getattr(scores, name)) for name in SCORES}


def object_size_cm(
    vision: ShapeEstimate | None,
    final: ShapeEstimate | None,
    true_mesh_world: trimesh.Trimesh | None = None,
) -> dict[str, list[float] | None]:
    """The object's extent (cm, 0.1 cm) along the estimate grid's axes (x horizontal toward the
    camera, y horizontal, z up): from vision, after the touches and, when known, the truth's
    along the same axes. An empty estimate's size is None."""

    def size(estimate: ShapeEstimate | None) -> list[float] | None:
        extent = (
            None if estimate is None else occupied_extent_m(estimate.probabilities, estimate.grid)
        )
        return None if extent is None else np.round(100.0 * extent, 1).tolist()

    sizes: dict[str, list[float] | None] = {"vision": size(vision), "final": size(final)}
    reference = final or vision
    if true_mesh_world is not None and reference is not None:
        true = extent_along_axes_m(true_mesh_world.vertices, reference.grid.axes_world)
        sizes["true"] = np.round(100.0 * true, 1).tolist()
    return sizes
