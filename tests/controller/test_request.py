"""Explore request validation: the whole request is checked before a session may start, and
every error names its field in a short line."""

from __future__ import annotations

import json

import pytest

from controller.request import (
    MAX_REQUEST_BYTES,
    ExploreRequest,
    RequestError,
    parse_explore_request,
)

PRIORS = frozenset({"auto", "general", "box"})  # as the learned perception lists them


def parse(body: bytes | str, priors: frozenset[str] = PRIORS) -> ExploreRequest:
    payload = body.encode() if isinstance(body, str) else body
    return parse_explore_request(payload, ExploreRequest(), priors=priors)


def test_valid_requests_over_the_defaults() -> None:
    assert parse(b"") == ExploreRequest()
    assert parse(b"  \n") == ExploreRequest()
    request = parse(json.dumps({"max_touches": 3, "prior": "box", "policy": "random"}))
    assert (request.max_touches, request.prior, request.policy) == (3, "box", "random")
    assert request.update == "global"  # the default
    for update in ("global", "fused", "prior", "direct"):
        assert parse(json.dumps({"update": update})).update == update


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            {"prior": "nosuchprior"},
            "'prior' must be one of 'auto', 'box', 'general', got 'nosuchprior'",
        ),
        ({"prior": "../../etc/passwd"}, "'prior' must be a name of 1..64 letters"),
        ({"prior": "x" * 65}, "'prior' must be a name of 1..64 letters"),
        ({"prior": ""}, "'prior' must be a name of 1..64 letters"),
        ({"prior": 3}, "'prior' must be a string"),
        ({"max_touches": 0}, "'max_touches' must be an integer in 1..100, got 0"),
        ({"max_touches": 101}, "'max_touches' must be an integer in 1..100, got 101"),
        ({"max_touches": "3"}, "'max_touches' must be an integer in 1..100, got '3'"),
        ({"max_touches": 2.5}, "'max_touches' must be an integer in 1..100, got 2.5"),
        ({"max_touches": True}, "'max_touches' must be an integer in 1..100, got True"),
        ({"policy": "greedy"}, "'policy' must be one of 'active', 'efficient', 'random'"),
        ({"update": "gp"}, "'update' must be one of 'global', 'fused', 'prior', 'direct'"),
        ({"touches": 3}, "unknown key 'touches'"),
    ],
)
def test_each_error_names_its_field(body: dict, message: str) -> None:
    with pytest.raises(RequestError) as error:
        parse(json.dumps(body))
    assert message in str(error.value)


def test_a_5000_digit_integer_gets_the_fields_wording() -> None:
    for sign in ("", "-"):
        with pytest.raises(RequestError) as error:
            parse('{"max_touches": ' + sign + "7" * 5000 + "}")
        assert str(error.value) == (
            "request: 'max_touches' must be an integer in 1..100, got a 5000-digit number"
        )


def test_duplicate_keys_are_refused() -> None:
    with pytest.raises(RequestError, match="duplicate key 'max_touches'"):
        parse('{"max_touches": 100, "max_touches": 1}')
    with pytest.raises(RequestError, match="duplicate key 'prior'"):
        parse('{"prior": "general", "prior": "nosuchprior"}')


def test_the_default_prior_is_checked_too() -> None:
    # An empty request takes the default prior: it must exist as much as a named one.
    with pytest.raises(RequestError, match="'prior' must be one of 'box'"):
        parse(b"", priors=frozenset({"box"}))


@pytest.mark.parametrize(
    "payload",
    [
        json.dumps({"prior": "x" * 1_000_000}).encode(),
        json.dumps({"x" * 10_000: 1}).encode(),
        json.dumps({"prior": "y" * 10_000}).encode(),
        b"[" * 10_000,
        b'{"a": ' * 3_000,
        b"\xff" * 1_000,
    ],
)
def test_errors_never_echo_long_input(payload: bytes) -> None:
    with pytest.raises(RequestError) as error:
        parse(payload)
    assert len(str(error.value)) < 200
    assert "\n" not in str(error.value)


def test_oversized_payloads_are_refused_before_parsing() -> None:
    with pytest.raises(RequestError, match=f"at most {MAX_REQUEST_BYTES}"):
        parse(b" " * (MAX_REQUEST_BYTES + 1))
