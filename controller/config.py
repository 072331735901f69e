"""The one configuration system: a typed tree of frozen dataclasses loaded from TOML.

Defaults describe the simulated bench, so an empty file (or none) runs the sim. Unknown keys and
bad values fail with a ``ConfigError`` naming the dotted key. Device sections are defined beside
their drivers (``drivers.config``); the rest lives here.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from drivers.config import (
    ArmConfig,
    CameraConfig,
    FieldError,
    GripperConfig,
    SensorConfig,
    SimConfig,
    Vec3,
    require_finite,
    require_positive,
)
from models.geometry import VoxelGrid, axes_facing_camera

NAME_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""Names a client or a config may give (priors): no paths, no spaces, bounded."""


class ConfigError(ValueError):
    """A configuration file is unreadable or has an unknown key or a bad value."""


@dataclass(frozen=True)
class Range:
    """Inclusive bounds of an ``Annotated[int, Range(...)]`` field: the validator checks the type
    and the bounds together, so every bad value gets the same wording ("an integer in 1..100")."""

    low: int
    high: int

    def __str__(self) -> str:
        return f"{self.low}..{self.high}"


@dataclass(frozen=True)
class RobotConfig:
    id: str = "sim"
    """Robot id used in Zenoh key expressions (touchshape/<id>/...)."""
    arm: ArmConfig = field(default_factory=ArmConfig)

    def __post_init__(self) -> None:
        if not self.id or any(c in self.id for c in "/*$?#"):
            raise FieldError("id", "must be a non-empty key-expression chunk (no / * $ ? #)")


@dataclass(frozen=True)
class CamerasConfig:
    rgbd: CameraConfig = field(default_factory=CameraConfig)


@dataclass(frozen=True)
class LimitsConfig:
    """Safety limits every motion is checked against (world frame, metres, seconds, newtons)."""

    workspace_min_world: Vec3 = (-0.40, -0.40, 0.0)
    workspace_max_world: Vec3 = (0.40, 0.40, 0.60)
    """Box the TCP must stay in."""
    max_tcp_speed_m_s: float = 0.25
    max_tcp_acceleration_m_s2: float = 1.0
    approach_speed_m_s: float = 0.02
    max_joint_speed_rad_s: float = 1.0
    max_force_n: float = 40.0
    """Gripper force that counts as a collision (fault)."""
    contact_force_n: float = 5.0
    """Gripper force that counts as a touch contact."""
    approach_contact_force_n: float = 0.2
    """Gripper force that stops the arm's approach (the fingers then make the contact): the
    first reading above the gripper's noise. On a face tilted to the pad, or an edge meeting
    the gel near its rim, the force grows slowly, and the rigid window behind the gel must not
    reach the object before a reading shows it; the arm moves 0.5 mm between readings."""
    unexpected_force_n: float = 15.0
    """On an approach, a TCP force this far above the reading at the approach's start, and
    above what the gel's finger feels, is a rigid part meeting the object: the arm stops and
    backs out along the approach line, and the target is dropped. Above the TCP force
    estimate's noise (a few newtons on an e-Series' sensor; raise it for a CB3, whose estimate
    from the joint currents is coarser) and well below a UR's protective-stop force."""
    table_clearance_m: float = 0.01
    shape_clearance_m: float = 0.01

    def __post_init__(self) -> None:
        # Written so that NaN fails: every comparison with NaN is false.
        require_finite(self, "workspace_min_world", "workspace_max_world")
        low, high = self.workspace_min_world, self.workspace_max_world
        if not all(lo < hi for lo, hi in zip(low, high, strict=True)):
            raise FieldError(
                "workspace_min_world", f"must be below workspace_max_world on every axis: {low}"
            )
        require_positive(
            self,
            "max_tcp_speed_m_s",
            "max_tcp_acceleration_m_s2",
            "approach_speed_m_s",
            "max_joint_speed_rad_s",
            "max_force_n",
            "contact_force_n",
            "approach_contact_force_n",
            "unexpected_force_n",
            "table_clearance_m",
            "shape_clearance_m",
        )
        if not self.approach_speed_m_s <= self.max_tcp_speed_m_s:
            raise FieldError(
                "approach_speed_m_s",
                f"must be at most max_tcp_speed_m_s ({self.max_tcp_speed_m_s}),"
                f" got {self.approach_speed_m_s}",
            )
        if not self.contact_force_n < self.max_force_n:
            raise FieldError(
                "contact_force_n",
                f"must be below max_force_n ({self.max_force_n}), got {self.contact_force_n}",
            )
        if not self.approach_contact_force_n <= self.contact_force_n:
            raise FieldError(
                "approach_contact_force_n",
                f"must be at most contact_force_n ({self.contact_force_n}),"
                f" got {self.approach_contact_force_n}",
            )


@dataclass(frozen=True)
class MotionConfig:
    """How a touch is made (the paper: stand off on the surface normal, approach progressively,
    make the final contact by opening the gripper slowly) and how the arm moves between touches."""

    approach_distance_m: float = 0.06
    """Pad distance from the target surface where the approach along the normal starts."""
    standoff_m: float = 0.005
    """Pad distance from the predicted surface where the arm stops and the fingers take over."""
    touch_width_m: float = 0.08
    """Finger opening during the arm's approach: the pad then protrudes past the gripper body."""
    finger_speed_m_s: float = 0.005
    """Finger opening speed for the final contact (the pad moves at half of it)."""
    direct_move_max_angle_deg: float = 30.0
    """Move directly between touches whose targets are closer than this around the vertical
    axis through the object point; otherwise detour above the object."""
    safe_height_margin_m: float = 0.05
    """Detours keep every tool part this far above the highest point of the shape estimate."""
    path_check_step_m: float = 0.01
    """Spacing of the poses checked along every straight-line motion."""
    refine_while_moving: bool = True
    """Refine the shape while the arm moves to the next target, chosen from the estimate before
    that refinement (every touch written in); false refines first, the arm waiting."""

    def __post_init__(self) -> None:
        require_positive(
            self,
            "approach_distance_m",
            "standoff_m",
            "finger_speed_m_s",
            "safe_height_margin_m",
            "path_check_step_m",
        )
        if not self.standoff_m < self.approach_distance_m:
            raise FieldError("standoff_m", "must be below approach_distance_m")
        if not (math.isfinite(self.touch_width_m) and self.touch_width_m >= 0):
            raise FieldError("touch_width_m", f"must be >= 0, got {self.touch_width_m}")
        if not 0 <= self.direct_move_max_angle_deg <= 180:
            raise FieldError("direct_move_max_angle_deg", "must be in [0, 180]")


@dataclass(frozen=True)
class VoxelGridConfig:
    resolution: int = 64
    extent_m: float = 0.26
    """Edge of the cubic grid; objects up to 25 cm tall and 20 cm wide fit the default."""
    object_point_world: Vec3 = (0.0, 0.0, 0.0)
    """Bottom centre of the grid on the table (o_w in the paper)."""

    def __post_init__(self) -> None:
        if not 8 <= self.resolution <= 256:
            raise FieldError("resolution", f"must be in [8, 256], got {self.resolution}")
        require_positive(self, "extent_m")
        require_finite(self, "object_point_world")

    def grid(self, camera_position_world: Vec3) -> VoxelGrid:
        """The registered grid; its axes follow the camera's yaw (the frame the prior uses)."""
        axes = axes_facing_camera(camera_position_world, self.object_point_world)
        return VoxelGrid(self.resolution, self.extent_m, self.object_point_world, axes)


@dataclass(frozen=True)
class ModelsConfig:
    prior: str = "auto"
    """The prior a session uses: a name in the weights folder's ``priors.json``, or "auto" (the
    one whose shape best explains each image, of all of the preset's; docs/prior.md)."""
    preset: Literal["cpu", "paper"] = "cpu"
    weights_dir: str = ""
    """Empty = the weights shipped with the package."""
    device: str = "cpu"
    compute_threads: int = 0
    """CPU threads of the session's perception, torch's and numpy's BLAS alike (0: half the
    cores, at most 4). Why not all: the devices' drivers (on the bench, its simulation) run
    beside it, and threads that wait on each other cost more than they bring: on a 2-core
    machine the main job's compute fell from 17.7-18.9 s to 12.9-14.1 s with one thread
    (docs/touch.md, "Cost")."""
    update: Literal["global", "fused", "prior", "direct"] = "global"
    """How touches change the shape (a request may choose another): "global" fits the prior's
    latent to every touch, takes that fit as the mean once it has predicted a touch it had not
    seen (models.touch.global_fit), then bends the mean's surface through every measurement;
    "fused" bends vision's surface only (models.touch.fused); "prior" the paper's latent-only
    update; "direct" the paper's Direct Edit baseline (docs/touch.md)."""
    fusion_support_m: float = 0.035
    """The fused correction's reach from a touch (models.touch.fused.FusionSettings)."""
    fusion_prior_std_m: float = 0.004
    """How far the prior's surface may be off before any touch (the fused field's
    uncertainty far from touches)."""
    global_learning_rate: float = 0.01
    """Adam's step size on the latent in the global update's fit (models.touch.global_fit)."""
    global_iterations: int = 15
    """Adam steps on the latent per round of the global update's fit (at most, with
    ``global_patience``)."""
    global_patience: int = 0
    """Stop the global update's fit once this many steps in a row have not improved on its
    best, and keep that best (0: every step, the last). Off: 3 meets the 0.5 s asked per
    touch but lowered the shapes a little on three of four sets (docs/touch.md, "Cost")."""
    global_camera_constraints: bool = True
    """Whether the camera's depth points constrain the global update's latent fit too (the fused
    correction passes through them in any case)."""
    stop_constraints: bool = True
    """Whether a touch the fingers' force stopped without an imprint on the gel tells the latent
    fits (and the guard) that the object reaches one of the tool's leading points there
    (``drivers.tool.ToolModel.leading_points_pad``). Off: only the sweep before the stop counts,
    as free space."""
    fusion_policy: Literal["committee", "variance", "window"] = "committee"
    """What the active policy reads with the fused update: the fused field's P(inside) with its
    uncertainty ("variance": touched regions are known), or with the prior's uncertainty
    everywhere ("window": the paper's |v - 0.5| policy on the fused shape). "committee" (the
    default): "variance", averaged with the global update's fit where the guard has not taken
    it, so windows where the two shapes disagree are uncertain and the next touch tests the fit
    (models.touch.global_fit.committee_probabilities; docs/touch.md, "The committee")."""
    refine_learning_rate: float = 3e-3
    """Adam's step size on the latent (the paper: 1e-3; docs/explore.md has the measured
    reason for 3e-3 together with the anchor)."""
    refine_iterations_per_touch: int = 10
    refine_loss: Literal["sum", "balanced", "threshold"] = "threshold"
    """The touch loss's form (models.touch.refinement.touch_loss): "sum" as the paper writes it;
    "balanced" (mean over empty + mean over occupied voxels), which keeps the many empty voxels
    of a touch from shrinking the shape; "threshold" (balanced, and a voxel stops pulling once
    it is on the right side of 0.5), which keeps the few contact voxels from inflating it
    (docs/explore.md)."""
    refine_anchor_weight: float = 0.03
    """Weight of the latent's squared distance to the vision latent in the refinement loss
    (models.touch.refinement.refine_latent); 0 = the paper's loss alone."""
    refine_write_measurements: bool = True
    """Write the touches' measured voxels into the refined shape (empty 0, occupied 1)."""
    aim_along_normal: bool = True
    """Approach each target along the fused shape's inward normal there (the active policy's
    directions are a lattice up to 45 degrees off it); off: along the policy's direction."""
    policy_stop_uncertainty: float = 0.0
    """The session stops before its touch budget when the active policy's most uncertain
    reachable window is less uncertain than this (0..1, see ``TouchTarget.uncertainty``);
    0 never stops early."""

    def __post_init__(self) -> None:
        if not NAME_PATTERN.fullmatch(self.prior):
            raise FieldError("prior", "must be 1..64 letters, digits, '_' or '-'")
        require_positive(self, "refine_learning_rate")
        require_positive(self, "global_learning_rate")
        if self.global_iterations < 0:
            raise FieldError("global_iterations", "must be >= 0")
        if self.global_patience < 0:
            raise FieldError("global_patience", "must be >= 0 (0: off)")
        if not 0 <= self.compute_threads <= 256:
            raise FieldError("compute_threads", "must be in [0, 256] (0: half the cores, <= 4)")
        require_positive(self, "fusion_support_m")
        require_positive(self, "fusion_prior_std_m")
        if self.refine_iterations_per_touch < 0:
            raise FieldError("refine_iterations_per_touch", "must be >= 0")
        if not (math.isfinite(self.refine_anchor_weight) and self.refine_anchor_weight >= 0):
            raise FieldError("refine_anchor_weight", "must be >= 0")
        if not 0.0 <= self.policy_stop_uncertainty <= 1.0:
            raise FieldError("policy_stop_uncertainty", "must be in [0, 1]")


@dataclass(frozen=True)
class MessagingConfig:
    """Eclipse Zenoh session of the service. Secrets stay out of this file: the password and
    the accepted-credentials dictionary are read from the files named here."""

    mode: Literal["peer", "client"] = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    user: str = ""
    """User name this session presents to its peers (Zenoh usrpwd authentication)."""
    password_file: str = ""
    """File holding the password of ``user``."""
    credentials_file: str = ""
    """Zenoh dictionary file of accepted ``user:password`` lines; when set, peers without
    valid credentials cannot open a session with the service."""
    tls_root_ca_certificate: str = ""
    tls_certificate: str = ""
    tls_private_key: str = ""
    """PEM files for tls/ endpoints (certificate and key also used for mutual TLS)."""
    tls_mutual: bool = False
    open_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        for name in ("listen", "connect"):
            for endpoint in getattr(self, name):
                problem = endpoint_problem(endpoint)
                if problem:
                    raise FieldError(name, f"endpoint {_short(endpoint)} {problem}")
        if bool(self.user) != bool(self.password_file):
            raise FieldError("password_file", "and user are set together")
        require_positive(self, "open_timeout_s")


_PORTED_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def endpoint_problem(endpoint: str) -> str | None:
    """What is wrong with a Zenoh endpoint ``<protocol>/<address>[?metadata][#config]``, or None;
    for IP protocols the address must end in a port 0..65535 (Zenoh's own errors do not
    always say which endpoint they mean)."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    protocol, slash, address = locator.partition("/")
    if not (protocol and slash and address):
        return "is not of the form <protocol>/<address>"
    if protocol in _PORTED_PROTOCOLS:
        host, colon, port = address.rpartition(":")
        digits = port.isascii() and port.isdigit() and len(port) <= 5
        if not (host and colon and digits and int(port) <= 65535):
            return "needs <host>:<port> with a port in 0..65535"
    return None


@dataclass(frozen=True)
class LoggingConfig:
    dir: str = "logs"
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    rerun: bool = True


@dataclass(frozen=True)
class Config:
    robot: RobotConfig = field(default_factory=RobotConfig)
    cameras: CamerasConfig = field(default_factory=CamerasConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    gripper: GripperConfig = field(default_factory=GripperConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    voxel_grid: VoxelGridConfig = field(default_factory=VoxelGridConfig)
    models: ModelsConfig = field(default_factory=ModelsConfig)
    messaging: MessagingConfig = field(default_factory=MessagingConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    sim: SimConfig = field(default_factory=SimConfig)


# --- loading --------------------------------------------------------------------------------------


def load_config(path: str | Path | None = None) -> Config:
    """Load a TOML config file over the sim defaults; None gives the defaults."""
    if path is None:
        return Config()
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"cannot read config file {path}: {error}") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML: {error}") from None
    return config_from_dict(data, source=str(path))


def config_from_dict(data: dict[str, Any], *, source: str = "config") -> Config:
    """Build the config tree from nested dicts (as parsed from TOML), checking every key."""
    return build_dataclass(Config, data, source=source)


def config_to_dict(config: Any) -> dict[str, Any]:
    """The config as nested plain dicts (tuples as lists), ready for TOML or JSON."""

    def plain(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return value

    return plain(config)


def config_to_toml(config: Config) -> str:
    """TOML text of a config (the effective config that `touchshape config show` prints)."""
    lines: list[str] = []

    def emit(table: dict[str, Any], prefix: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        if scalars and prefix:
            lines.append(f"\n[{prefix}]")
        for key, value in scalars.items():
            lines.append(f"{key} = {_toml_value(value)}")
        for key, value in table.items():
            if isinstance(value, dict):
                emit(value, f"{prefix}.{key}" if prefix else key)

    emit(config_to_dict(config), "")
    return "\n".join(lines).lstrip() + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def build_dataclass(
    cls: type, data: Any, *, prefix: str = "", source: str, error: type[ValueError] = ConfigError
) -> Any:
    """Build the frozen dataclass ``cls`` from plain data (parsed TOML or JSON), checking every
    key against its type hints; ``error`` names the dotted key of anything unknown or wrong.
    The one validator of configs and requests."""
    if not isinstance(data, dict):
        where = f"[{prefix}]" if prefix else "the top level"
        raise error(f"{source}: {where} must be a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls, include_extras=True)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        key = f"{prefix}.{unknown[0]}" if prefix else unknown[0]
        raise error(f"{source}: unknown key {_short(key)} (known: {', '.join(sorted(names))})")
    values = {}
    for name, raw in data.items():
        key = f"{prefix}.{name}" if prefix else name
        values[name] = _coerce(hints[name], raw, key=key, source=source, error=error)
    try:
        return cls(**values)
    except FieldError as failure:
        key = f"{prefix}.{failure.field}" if prefix else failure.field
        raise error(f"{source}: '{key}' {failure.message}") from None
    except ValueError as failure:
        where = prefix or "config"
        raise error(f"{source}: bad value in [{where}]: {failure}") from None


def _short(value: Any, limit: int = 40) -> str:
    """``repr`` cut to ``limit`` characters: errors never echo a megabyte of input."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}..."


def _coerce(hint: Any, raw: Any, *, key: str, source: str, error: type[ValueError]) -> Any:
    def bad(expected: str) -> ValueError:
        return error(f"{source}: '{key}' must be {expected}, got {_short(raw)}")

    def inner(inner_hint: Any, value: Any) -> Any:
        return _coerce(inner_hint, value, key=key, source=source, error=error)

    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        return build_dataclass(hint, raw, prefix=key, source=source, error=error)
    if origin is Annotated:  # an integer and its Range
        bounds = typing.get_args(hint)[1]
        is_int = isinstance(raw, int) and not isinstance(raw, bool)
        if not (is_int and bounds.low <= raw <= bounds.high):
            raise bad(f"an integer in {bounds}")
        return raw
    if origin is Literal:
        if raw not in typing.get_args(hint):
            raise bad("one of " + ", ".join(repr(a) for a in typing.get_args(hint)))
        return raw
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(hint) if a is not type(None)]
        return inner(options[0], raw)
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(raw, list):
            raise bad("an array")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(inner(args[0], v) for v in raw)
        if len(raw) != len(args):
            raise bad(f"an array of {len(args)} values")
        return tuple(inner(a, v) for a, v in zip(args, raw, strict=True))
    if hint is bool:
        if not isinstance(raw, bool):
            raise bad("true or false")
        return raw
    if hint is int:
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise bad("an integer")
        return raw
    if hint is float:
        if isinstance(raw, bool) or not isinstance(raw, int | float):
            raise bad("a number")
        # NaN passes every "x <= limit" check and inf every "x > 0": no limit may be either.
        try:
            value = float(raw)
        except OverflowError:
            raise bad("a finite number") from None
        if not math.isfinite(value):
            raise bad("a finite number")
        return value
    if hint is str:
        if not isinstance(raw, str):
            raise bad("a string")
        return raw
    raise error(f"{source}: '{key}' has an unsupported type {hint!r}")  # a bug in the dataclass
