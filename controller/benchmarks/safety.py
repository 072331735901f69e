"""`touchshape bench safety`: how near the tool comes to the object in full exploration sessions
on the simulated bench.

Each session is what `touchshape explore` runs (``TouchshapeService`` with the given perception,
the simulated devices), on one object turned by one yaw, in a fresh service: the world is built
from the config's ``[sim]`` object and yaw at start-up. Afterwards the session's arm motions
(``motions.jsonl``) are replayed against the *true* object mesh: for every rigid tool part, its
least distance from the object's surface along each motion. Transits are meant to keep clear of
the object; the approach and the retract are meant to bring the gel (only) to it. A session that
faults or cannot run is reported with its error and the run goes on.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import re
import time
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

from controller.config import Config
from controller.request import ExploreRequest
from controller.service import PerceptionFactory, TouchshapeService
from drivers.config import ArmConfig
from drivers.sim.arm import SimUR5
from drivers.tool import ToolBox, ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import rotation_angle_between, ur_pose_to_matrix
from models.procedural import CATEGORIES
from models.shapes import load_mesh_file

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

SURFACE_SPACING_M = 0.001
"""Mean spacing of the points sampled on the object's surface: a clearance is measured to these
and the mesh's vertices (so the object's corners count exactly). A box face parallel to the
surface measures its gap exactly; elsewhere a sample gap of ~1 mm shifts a clearance of d by
about gap^2 / 2d, well under a millimetre except within a millimetre or two of contact."""
SEARCH_M = 0.1
"""Clearances are exact up to this; a larger one is reported as a lower bound (at least this):
far from the object only "far" matters, and exact figures there would cost most of the time."""
POSE_STEP_M = 0.002
"""Poses along a motion are checked this far apart (TCP travel, or tool reach when turning)."""
TOOL_REACH_M = 0.17
"""Flange to fingertip: a radian of tool rotation sweeps the tip about this far (the planner
checks its lines with the same figure; kept here so the benchmark measures what the arm does,
whatever the planner's modules become)."""
JOINT_REACH_M = 1.1
"""No tool point is further than this from any UR5 joint axis (0.85 m reach plus the tool):
bounds how far a tool point moves per radian of a joint move."""
TOUCH_LABELS = ("approach", "retract")
"""The force-checked final approach and its way back: the gel is meant to touch there."""
TOUCHING_PARTS = ("gelsight_window",)
"""The rigid part right behind the gel: on an approach it comes within the gel's give of the
surface by design, so it is left out of the approach clearances."""


# --- clearance ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on an object's surface, their k-d tree, and the mesh when it is a closed solid
    (then a tool part buried whole inside it is found too)."""

    points: FloatArray
    tree: cKDTree
    solid: trimesh.Trimesh | None

    @classmethod
    def of_mesh(
        cls, mesh: trimesh.Trimesh, spacing_m: float = SURFACE_SPACING_M, seed: int = 0
    ) -> SurfaceSamples:
        count = max(1, math.ceil(float(mesh.area) / spacing_m**2))
        sampled, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
        points = np.concatenate([np.asarray(sampled, float), np.asarray(mesh.vertices, float)])
        return cls(points, cKDTree(points), mesh if mesh.is_watertight else None)


def box_signed_distances(points_box: FloatArray, half_extents: FloatArray) -> FloatArray:
    """Signed distance of points (box frame, N x 3) from an axis-aligned box centred at the
    origin: positive outside, negative inside (minus the depth to the nearest face)."""
    excess = np.abs(points_box) - half_extents
    outside = np.linalg.norm(np.maximum(excess, 0.0), axis=-1)
    return outside + np.minimum(np.max(excess, axis=-1), 0.0)


def box_clearance_m(
    pose_world_box: FloatArray,
    half_extents: FloatArray,
    samples: SurfaceSamples,
    search_m: float = SEARCH_M,
) -> float:
    """Least distance (metres) of an oriented box from the surface points; zero or negative
    when the box meets the object (a surface point inside it, or its centre inside the solid).
    Exact up to ``search_m``; beyond it a lower bound that is at least ``search_m``."""
    half = np.asarray(half_extents, dtype=float)
    half_diagonal = float(np.linalg.norm(half))
    centre, rotation = pose_world_box[:3, 3], pose_world_box[:3, :3]

    def distances(indices: Any) -> FloatArray:
        return box_signed_distances((samples.points[indices] - centre) @ rotation, half)

    nearest_m, nearest = samples.tree.query(centre)
    best = float(distances([nearest])[0])
    # A point nearer the box than ``best`` lies within ``best`` + half-diagonal of its centre.
    radius = half_diagonal + min(max(best, 0.0), search_m)
    near = samples.tree.query_ball_point(centre, radius)
    if near:
        best = min(best, float(np.min(distances(near))))
    if best > search_m:  # everything found is past the search: only a bound is known
        best = max(search_m, float(nearest_m) - half_diagonal)
    solid = samples.solid
    if best > 0.0 and solid is not None and _within(centre, solid.bounds):
        # Buried: no surface point inside the box, but its centre inside the object.
        return -best if solid.contains([centre])[0] else best
    return best


def _within(point: FloatArray, bounds: FloatArray) -> bool:
    return bool(np.all(point >= bounds[0]) and np.all(point <= bounds[1]))


def line_poses(
    start_world_tcp: FloatArray, end_world_tcp: FloatArray, step_m: float = POSE_STEP_M
) -> FloatArray:
    """TCP poses (P x 4 x 4) along a straight line with the orientation slerped (as moveL
    moves and the planner checks), at most ``step_m`` of TCP travel apart, and closer when
    the tool turns (a radian sweeps the fingertips ``TOOL_REACH_M``)."""
    start, end = np.asarray(start_world_tcp, float), np.asarray(end_world_tcp, float)
    distance = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
    angle = rotation_angle_between(start[:3, :3], end[:3, :3])
    steps = max(1, math.ceil(max(distance, TOOL_REACH_M * angle) / step_m))
    fractions = np.linspace(0.0, 1.0, steps + 1)
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([start[:3, :3], end[:3, :3]])))
    poses = np.tile(np.eye(4), (len(fractions), 1, 1))
    poses[:, :3, :3] = slerp(fractions).as_matrix()
    poses[:, :3, 3] = start[:3, 3] + fractions[:, None] * (end[:3, 3] - start[:3, 3])
    return poses


def joint_move_poses(
    start_joints_rad: FloatArray,
    end_joints_rad: FloatArray,
    arm: ArmConfig,
    step_m: float = POSE_STEP_M,
) -> FloatArray:
    """TCP poses (world, P x 4 x 4) along a joint move (moveJ: linear in the joints), close
    enough that no tool point within ``JOINT_REACH_M`` of every joint axis travels more than
    ``step_m`` between two of them."""
    start, end = np.asarray(start_joints_rad, float), np.asarray(end_joints_rad, float)
    steps = max(1, math.ceil(float(np.sum(np.abs(end - start))) * JOINT_REACH_M / step_m))
    pose_world_base = ur_pose_to_matrix(arm.pose_world_base)
    pose_flange_tcp = ur_pose_to_matrix(arm.tcp_offset)
    return np.stack(
        [
            pose_world_base @ forward_kinematics(start + s * (end - start)) @ pose_flange_tcp
            for s in np.linspace(0.0, 1.0, steps + 1)
        ]
    )


def motion_poses(motion: dict[str, Any], arm: ArmConfig) -> FloatArray:
    """The TCP poses along one ``motions.jsonl`` record: a joint move's from its joints, any
    other a straight TCP line (a joint move logged without its joints is taken as a line)."""
    if motion.get("kind") == "joints" and "start_joints_rad" in motion:
        return joint_move_poses(motion["start_joints_rad"], motion["end_joints_rad"], arm)
    return line_poses(np.asarray(motion["start_world_tcp"]), np.asarray(motion["end_world_tcp"]))


def motion_clearances(
    start_world_tcp: FloatArray,
    end_world_tcp: FloatArray,
    boxes: Sequence[ToolBox],
    samples: SurfaceSamples,
    *,
    step_m: float = POSE_STEP_M,
    search_m: float = SEARCH_M,
) -> dict[str, float]:
    """Each box's least clearance (metres) along one straight motion (:func:`line_poses`)."""
    poses = line_poses(start_world_tcp, end_world_tcp, step_m)
    return poses_clearances(poses, boxes, samples, search_m)


def poses_clearances(
    poses: FloatArray,
    boxes: Sequence[ToolBox],
    samples: SurfaceSamples,
    search_m: float = SEARCH_M,
) -> dict[str, float]:
    """Each box's least clearance (metres, :func:`box_clearance_m`) over TCP poses. Poses are
    ranked by a lower bound (nearest surface point to the box centre, less the half-diagonal)
    and measured exactly only while that bound is below the least clearance found so far: the
    rest cannot be nearer."""
    result = {}
    for box in boxes:
        poses_box = poses @ box.pose_tcp_box
        centres = poses_box[:, :3, 3]
        nearest_m, nearest = samples.tree.query(centres)
        offsets = samples.points[nearest] - centres
        upper = box_signed_distances(
            np.einsum("pi,pij->pj", offsets, poses_box[:, :3, :3]), box.half_extents_m
        )
        lower = nearest_m - float(np.linalg.norm(box.half_extents_m))
        # The least upper bound is a real point's distance: the least clearance is no larger.
        best = float(np.min(upper))
        for index in np.argsort(lower):
            if lower[index] >= best:
                break
            clearance = box_clearance_m(poses_box[index], box.half_extents_m, samples, search_m)
            best = min(best, clearance)
        result[box.name] = best
    return result


def _mm(value_m: float) -> float:
    return round(value_m * 1e3, 2)


def session_clearances(
    motions: Sequence[dict[str, Any]],
    tool: ToolModel,
    samples: SurfaceSamples,
    arm: ArmConfig,
) -> dict[str, Any]:
    """Clearances of one session's motions (records of ``motions.jsonl``), in mm: least over
    transits per part and overall, with the worst transit (its index in the file, label and
    part); least over the approaches and retracts per part, the gel's window left out."""
    transit: dict[str, float] = {}
    approach: dict[str, float] = {}
    worst: dict[str, Any] | None = None
    transits = 0
    for index, motion in enumerate(motions):
        boxes = tool.rigid_boxes(float(motion["width_m"]))
        touching = motion["label"] in TOUCH_LABELS
        if touching:
            boxes = [b for b in boxes if b.name not in TOUCHING_PARTS]
        clearances = poses_clearances(motion_poses(motion, arm), boxes, samples)
        least = approach if touching else transit
        for part, clearance in clearances.items():
            least[part] = min(least.get(part, math.inf), clearance)
        if touching:
            continue
        transits += 1
        part = min(clearances, key=clearances.__getitem__)
        if worst is None or clearances[part] < worst["clearance_m"]:
            worst = {"motion": index, "label": motion["label"], "part": part}
            worst["clearance_m"] = clearances[part]
    if worst is not None:
        worst["clearance_mm"] = _mm(worst.pop("clearance_m"))
    return {
        "motions": len(motions),
        "transit_motions": transits,
        "joint_motions": sum(motion.get("kind") == "joints" for motion in motions),
        "min_transit_clearance_mm": _mm(min(transit.values())) if transit else None,
        "min_transit_clearance_by_part_mm": {p: _mm(c) for p, c in transit.items()},
        "worst_transit": worst,
        "min_approach_clearance_mm": _mm(min(approach.values())) if approach else None,
        "min_approach_clearance_by_part_mm": {p: _mm(c) for p, c in approach.items()},
    }


def read_motions(path: Path) -> list[dict[str, Any]]:
    """The records of a ``motions.jsonl`` (none when the session made no motion)."""
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


# --- sessions -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SafetyObject:
    """What the sim bench stands on the table: a procedural category or a mesh file, with the
    file's up axis and scale (``[sim]`` object, object_up_axis, object_scale)."""

    name: str
    spec: str
    up_axis: str = "z"
    scale: float = 1.0


def safety_objects(
    categories: Sequence[str] | None,
    files: Sequence[str | Path] | None,
    *,
    up_axis: str = "z",
    fit_size_m: float | None = None,
) -> list[SafetyObject]:
    """The categories (all when neither is given) and the mesh files, scaled as the
    exploration benchmark scales them (``file_objects``: ``fit_size_m``, or down to the grid)."""
    from controller.benchmarks.explore import file_objects

    if not categories and not files:
        categories = CATEGORIES
    objects = [SafetyObject(name, name) for name in categories or ()]
    for path in files or ():
        (fitted,) = file_objects([path], up_axis=up_axis, fit_size_m=fit_size_m)
        loaded = load_mesh_file(path, up_axis=up_axis)
        scale = float(np.max(fitted.mesh.extents) / np.max(loaded.extents))
        objects.append(SafetyObject(fitted.name, str(path), up_axis, scale))
    return objects


@dataclass(frozen=True)
class SafetySettings:
    """What the benchmark runs (the CLI's options)."""

    touches: int = 10
    yaws: int = 1
    """Sessions per object, each at a yaw drawn from ``seed`` and the object's name."""
    seed: int = 0
    input_mode: Literal["rgb", "rgbd"] = "rgb"

    def __post_init__(self) -> None:
        low, high = ExploreRequest.MAX_TOUCHES_RANGE
        if not low <= self.touches <= high:
            raise ValueError(f"touches must be in {low}..{high}")
        if self.yaws < 1:
            raise ValueError("yaws must be >= 1")


def object_yaws_deg(name: str, settings: SafetySettings) -> list[float]:
    """The object's yaws: seeded by its name, so a run on fewer objects repeats these."""
    rng = np.random.default_rng((settings.seed, zlib.crc32(name.encode())))
    return [round(float(yaw), 2) for yaw in rng.uniform(0.0, 360.0, settings.yaws)]


@dataclass
class SessionRun:
    """What one session left: its summary, the arm's protective stops, the true object."""

    summary: dict[str, Any] | None = None
    protective_stops: list[str] | None = None
    rigid_contacts: list[str] | None = None
    """Every contact of a rigid tool part with the object or the table the arm pressed on
    into, protective stop or not (a contact the approach felt and backed out of included)."""
    object_mesh_world: trimesh.Trimesh | None = None
    error: str | None = None


async def run_session(
    config: Config,
    request: ExploreRequest,
    perception_factory: PerceptionFactory,
    logs_dir: Path,
    rng_seed: int,
) -> SessionRun:
    """One session in a fresh service (devices, world, perception); what went wrong is kept
    in the result, never raised, so the benchmark goes on."""
    run = SessionRun()
    service: TouchshapeService | None = None
    try:
        service = TouchshapeService(
            config, perception_factory, logs_dir=logs_dir, rng_seed=rng_seed
        )
        await service.start()
        service.start_session(request)
        run.summary = await service.wait_session()
        devices = service.devices
        assert devices is not None and devices.world is not None
        # Read after the session: the object the arm met, whatever built or replaced it.
        run.object_mesh_world = devices.world.object_mesh_world
        if isinstance(devices.arm, SimUR5):
            run.protective_stops = [
                f"{stop.part} hit the {stop.obstacle}" for stop in devices.arm.protective_stops
            ]
            run.rigid_contacts = [
                f"{contact.part} met the {contact.obstacle}"
                for contact in devices.arm.rigid_contacts
            ]
    except Exception as error:  # reported with the session, the next one still runs
        log.exception("session failed to run")
        run.error = f"{type(error).__name__}: {error}"
    finally:
        try:
            if service is not None:
                await service.stop()
        except Exception as error:
            log.exception("service stop failed")
            run.error = run.error or f"stop failed: {type(error).__name__}: {error}"
    return run


def session_row(
    obj: SafetyObject,
    yaw_deg: float,
    run: SessionRun,
    config: Config,
    logs_dir: Path,
) -> dict[str, Any]:
    """One session's JSON row."""
    tool = ToolModel(config.gripper, config.sensor)
    summary = run.summary or {}
    stops = run.protective_stops
    row: dict[str, Any] = {
        "object": obj.name,
        "yaw_deg": yaw_deg,
        "session": summary.get("session"),
        "state": summary.get("state", "error"),
        "touches": summary.get("touches", 0),
        "contacts": summary.get("contacts", 0),
        "error": summary.get("error") or run.error,
        "protective_stops": None if stops is None else len(stops),
        "protective_stop_parts": stops,
        "rigid_contacts": run.rigid_contacts or [],  # none when the arm never moved
        "unexpected_forces": len(summary.get("unexpected_forces", [])),
        "stop_reason": summary.get("stop_reason"),
        "skipped_targets": summary.get("skipped_targets", []),
    }
    clearances: dict[str, Any] = {"min_transit_clearance_mm": None}
    if run.summary is not None and run.object_mesh_world is not None:
        try:
            motions = read_motions(logs_dir / str(summary["session"]) / "motions.jsonl")
            samples = SurfaceSamples.of_mesh(run.object_mesh_world)
            clearances = session_clearances(motions, tool, samples, config.robot.arm)
        except Exception as error:  # a broken log must not end the run
            log.exception("clearances of %s failed", summary.get("session"))
            clearances["clearance_error"] = f"{type(error).__name__}: {error}"
    row.update(clearances)
    return row


def run_safety_benchmark(
    config: Config,
    objects: Sequence[SafetyObject],
    settings: SafetySettings,
    *,
    perception_factory: PerceptionFactory,
    logs_dir: Path,
    progress: Callable[[dict[str, Any]], None] = lambda row: None,
) -> dict[str, Any]:
    """One session per object and yaw (``progress`` gets each row as it ends); the JSON:
    the rows (``sessions_run``) and the totals (:func:`summarise_safety`)."""
    rows = []
    for obj in objects:
        for index, yaw_deg in enumerate(object_yaws_deg(obj.name, settings)):
            sim = replace(
                config.sim,
                object=obj.spec,
                object_up_axis=obj.up_axis,
                object_scale=obj.scale,
                object_yaw_deg=yaw_deg,
            )
            request = ExploreRequest(
                max_touches=settings.touches,
                input=settings.input_mode,
                prior=config.models.prior,
            )
            seed = int(
                np.random.SeedSequence(
                    [settings.seed, zlib.crc32(obj.name.encode()), index]
                ).generate_state(1)[0]
            )
            started = time.perf_counter()
            run = asyncio.run(
                run_session(replace(config, sim=sim), request, perception_factory, logs_dir, seed)
            )
            row = session_row(obj, yaw_deg, run, config, logs_dir)
            row["wall_s"] = round(time.perf_counter() - started, 1)
            rows.append(row)
            progress(row)
    return summarise_safety(rows, settings)


def _reason_kind(reason: object) -> str:
    """A skip reason with its figures replaced by "#": reasons that differ only in how near a
    part would come are counted together (each session keeps the full reasons)."""
    return re.sub(r"-?\d+(\.\d+)?", "#", str(reason))


def _least(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return min(known) if known else None


def summarise_safety(rows: Sequence[dict[str, Any]], settings: SafetySettings) -> dict[str, Any]:
    """The totals over sessions, then the rows themselves."""
    states = Counter(row["state"] for row in rows)
    touches = sum(row["touches"] for row in rows)
    contacts = sum(row["contacts"] for row in rows)

    def least_by_part(key: str) -> dict[str, float | None]:
        parts = sorted({part for row in rows for part in row.get(key, {})})
        return {part: _least([row.get(key, {}).get(part) for row in rows]) for part in parts}

    skipped = [t for row in rows for t in row["skipped_targets"]]
    return {
        "sessions": len(rows),
        "states": dict(states),
        "faults": states.get("fault", 0),
        "aborted": states.get("aborted", 0),
        "errors": states.get("error", 0),
        "protective_stops": sum(row["protective_stops"] or 0 for row in rows),
        # None when a session (a run merged from before these were counted) did not count.
        "rigid_contacts": _total([_count(row.get("rigid_contacts")) for row in rows]),
        "unexpected_forces": _total([row.get("unexpected_forces") for row in rows]),
        "min_transit_clearance_mm": _least([row["min_transit_clearance_mm"] for row in rows]),
        "min_transit_clearance_by_part_mm": least_by_part("min_transit_clearance_by_part_mm"),
        "min_approach_clearance_mm": _least([row.get("min_approach_clearance_mm") for row in rows]),
        "min_approach_clearance_by_part_mm": least_by_part("min_approach_clearance_by_part_mm"),
        "touches": touches,
        "contacts": contacts,
        "contact_fraction": round(contacts / touches, 3) if touches else None,
        "skipped_targets": len(skipped),
        "skipped_reasons": dict(Counter(_reason_kind(t.get("reason")) for t in skipped)),
        # Sessions whose summary gives no stop reason are counted under "none".
        "stop_reasons": dict(Counter(str(row["stop_reason"] or "none") for row in rows)),
        "config": {
            "touches": settings.touches,
            "yaws": settings.yaws,
            "seed": settings.seed,
            "input": settings.input_mode,
            "surface_spacing_mm": SURFACE_SPACING_M * 1e3,
            "pose_step_mm": POSE_STEP_M * 1e3,
            "exact_up_to_mm": SEARCH_M * 1e3,
        },
        "sessions_run": list(rows),
    }


def _count(items: list[Any] | None) -> int | None:
    return None if items is None else len(items)


def _total(counts: list[int | None]) -> int | None:
    return None if any(count is None for count in counts) else sum(counts)  # type: ignore[misc]


def format_row(row: dict[str, Any]) -> str:
    """One session as a line of the table (:data:`TABLE_HEADER`)."""
    worst = row.get("worst_transit") or {}
    where = f"{worst.get('part')}@{worst.get('label')}#{worst.get('motion')}" if worst else "-"
    stops = row["protective_stops"]
    return (
        f"{row['object']:<12} {row['yaw_deg']:>6.1f} {row['state']:<7} "
        f"{row['touches']:>3}/{row['contacts']:<3} {'?' if stops is None else stops:>5} "
        f"{_number(row['min_transit_clearance_mm']):>8} {where:<36} "
        f"{_number(row.get('min_approach_clearance_mm')):>8} {len(row['skipped_targets']):>4} "
        f"{row['stop_reason'] or '-'} {row['error'] or ''}"
    ).rstrip()


TABLE_HEADER = (
    f"{'object':<12} {'yaw':>6} {'state':<7} {'t/c':<7} {'stops':>5} {'transit':>8} "
    f"{'worst transit (part@label#motion)':<36} {'approach':>8} {'skip':>4} stop reason, error"
)


def _maybe(count: int | None) -> str:
    return "?" if count is None else str(count)


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def format_table(result: dict[str, Any]) -> str:
    """The sessions, one line each (clearances in mm), and the totals."""
    lines = [TABLE_HEADER, *(format_row(row) for row in result["sessions_run"])]
    lines.append(
        f"{result['sessions']} sessions: {result['states']}, {result['protective_stops']} "
        f"protective stops, {_maybe(result.get('rigid_contacts'))} rigid-part contacts "
        f"({_maybe(result.get('unexpected_forces'))} felt on an approach), {result['touches']} "
        f"touches ({result['contacts']} contacts), "
        f"{result['skipped_targets']} targets skipped; least transit clearance "
        f"{_number(result['min_transit_clearance_mm'])} mm, approach (window excluded) "
        f"{_number(result['min_approach_clearance_mm'])} mm"
    )
    return "\n".join(lines)
