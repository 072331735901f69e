"""What a client may ask of an exploration session, and the validation of a request body."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import ClassVar, Literal

from controller.config import build_dataclass


class RequestError(ValueError):
    """A request is not valid JSON, has unknown fields or out-of-range values."""


@dataclass(frozen=True)
class ExploreRequest:
    """What a client may ask of an exploration session; every field is optional."""

    max_touches: int = 10
    policy: Literal["active", "random"] = "active"
    update: Literal["prior", "direct"] = "prior"
    input: Literal["rgb", "rgbd"] = "rgb"
    prior: str = "general"

    MAX_TOUCHES_RANGE: ClassVar[tuple[int, int]] = (1, 100)

    def __post_init__(self) -> None:
        low, high = self.MAX_TOUCHES_RANGE
        if not low <= self.max_touches <= high:
            raise ValueError(f"max_touches must be in {low}..{high}, got {self.max_touches}")
        if not self.prior:
            raise ValueError("prior must be a non-empty string")


def parse_explore_request(payload: bytes, defaults: ExploreRequest) -> ExploreRequest:
    """Validate an explore request body (JSON object, may be empty) over the defaults."""
    if not payload.strip():
        return defaults
    try:
        body = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise RequestError(f"request is not valid JSON: {error}") from None
    if not isinstance(body, dict):
        raise RequestError("request must be a JSON object")
    merged = {**defaults.__dict__, **body}
    return build_dataclass(ExploreRequest, merged, source="request", error=RequestError)
