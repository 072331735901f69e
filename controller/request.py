"""What a client may ask of an exploration session, and the validation of a request body."""

from __future__ import annotations

import json
from collections.abc import Collection
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

from controller.config import NAME_PATTERN, Range, build_dataclass
from drivers.config import FieldError

MAX_REQUEST_BYTES = 16384
"""A request is a few short fields; anything much longer is refused before it is parsed (a
5000-digit number still gets its field's error)."""

MAX_TOUCHES = Range(1, 100)


class RequestError(ValueError):
    """A request is not valid JSON, has unknown fields or out-of-range values."""


@dataclass(frozen=True)
class ExploreRequest:
    """What a client may ask of an exploration session; every field is optional."""

    max_touches: Annotated[int, MAX_TOUCHES] = 10
    policy: Literal["active", "efficient", "random"] = "active"
    """active: the paper's (the least confident window); efficient: the most expected
    uncertainty reduction per second of robot time (the planner's); random: the baseline."""
    update: Literal["global", "fused", "prior", "direct"] = "global"
    input: Literal["auto", "rgb", "rgbd"] = "auto"
    """auto: RGB-D when the camera gives depth (the Kinect v2 and the bench do), RGB otherwise."""
    prior: str = "auto"

    MAX_TOUCHES_RANGE: ClassVar[tuple[int, int]] = (MAX_TOUCHES.low, MAX_TOUCHES.high)

    def __post_init__(self) -> None:
        if not MAX_TOUCHES.low <= self.max_touches <= MAX_TOUCHES.high:
            raise FieldError("max_touches", f"must be an integer in {MAX_TOUCHES}")
        if not NAME_PATTERN.fullmatch(self.prior):
            raise FieldError(
                "prior",
                f"must be a name of 1..64 letters, digits, '_' or '-', got {self.prior[:40]!r}",
            )


class _LongNumber:
    """A JSON number too long for Python's int conversion (over 4300 digits): it fails the
    field's own type check, so the error is the field's, not the interpreter's."""

    def __init__(self, text: str) -> None:
        self.digits = len(text.lstrip("-"))

    def __repr__(self) -> str:
        return f"a {self.digits}-digit number"


def _parse_int(text: str) -> int | _LongNumber:
    return int(text) if len(text) <= 100 else _LongNumber(text)


def _refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    body: dict[str, Any] = {}
    for key, value in pairs:
        if key in body:
            raise RequestError(f"request: duplicate key {key[:40]!r}")
        body[key] = value
    return body


def parse_explore_request(
    payload: bytes, defaults: ExploreRequest, *, priors: Collection[str]
) -> ExploreRequest:
    """Validate an explore request body (JSON object, may be empty) over the defaults; the prior
    must be one of ``priors``. Errors name the field and never echo more than a few characters
    of the input."""
    if len(payload) > MAX_REQUEST_BYTES:
        raise RequestError(
            f"request is too large: {len(payload)} bytes (at most {MAX_REQUEST_BYTES})"
        )
    if not payload.strip():
        body: Any = {}
    else:
        try:
            body = json.loads(payload, object_pairs_hook=_refuse_duplicates, parse_int=_parse_int)
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise RequestError(f"request is not valid JSON: {error}") from None
        except RecursionError:
            raise RequestError("request is not valid JSON: nested too deeply") from None
    if not isinstance(body, dict):
        raise RequestError("request must be a JSON object")
    merged = {**defaults.__dict__, **body}
    request = build_dataclass(ExploreRequest, merged, source="request", error=RequestError)
    if request.prior not in priors:
        known = ", ".join(repr(name) for name in sorted(priors)) or "(no prior is installed)"
        raise RequestError(f"request: 'prior' must be one of {known}, got {request.prior!r}")
    return request
