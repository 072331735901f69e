"""The service over a real Zenoh session on loopback: the API as a remote client sees it."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest

from controller.config import Config, MessagingConfig
from controller.messaging import EndpointError, open_session
from controller.service import TouchshapeService, decode_shape
from tests.fakes.perception import make_cylinder_perception
from tests.fakes.zenoh_client import Client, free_port

WORKING = ["capture", "reconstruct", "select", "approach", "touch", "refine"]


async def wait_for(predicate, timeout_s: float = 60.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not predicate():
            await asyncio.sleep(0.02)


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[tuple[TouchshapeService, MessagingConfig]]:
    port = free_port()
    config = Config()
    config = dataclasses.replace(
        config,
        sim=dataclasses.replace(config.sim, object="can"),
        messaging=MessagingConfig(listen=(f"tcp/127.0.0.1:{port}",)),
    )
    service = TouchshapeService(config, make_cylinder_perception, logs_dir=tmp_path)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.serve(stop, ready))
    await asyncio.wait_for(ready.wait(), 60)
    yield service, MessagingConfig(listen=(), connect=(f"tcp/127.0.0.1:{port}",))
    stop.set()
    await task


async def test_remote_session_end_to_end(served) -> None:
    _, client_config = served
    client = await asyncio.to_thread(Client, client_config)
    try:
        await asyncio.sleep(0.3)  # let the subscription reach the service
        assert (await client.aquery("status"))[0]["state"] == "idle"
        reply = (await client.aquery("explore", json.dumps({"max_touches": 2})))[0]
        assert reply["accepted"] is True
        await wait_for(lambda: "result" in client.messages)
        states = [m for m in client.messages["state"] if m["session"] == reply["session"]]
        names = [m["state"] for m in states]
        assert names[: len(WORKING)] == WORKING
        assert names[-2:] == ["done", "idle"]
        assert all({"session", "state", "previous", "touch", "time"} <= set(m) for m in states)
        assert len(client.messages["touch"]) == 2
        shape = decode_shape(client.messages["shape"][-1])
        assert shape.shape == (64, 64, 64) and shape.max() <= 1.0
        result = client.messages["result"][0]
        rrd = result["artifacts"]["recording"]
        assert rrd.endswith(".rrd")
        assert Path(result["artifacts"]["picture"]).name == "shape.png"
        assert Path(result["artifacts"]["picture"]).is_file()
        # The sim scores every estimate: vision (touch 0) and after each of the 2 touches.
        scores = [m for m in client.messages["score"] if m["session"] == reply["session"]]
        assert sorted(m["touch"] for m in scores) == [0, 1, 2]
        rerun = Path(sys.executable).with_name("rerun")
        verified = await asyncio.to_thread(
            subprocess.run, [str(rerun), "rrd", "verify", rrd], capture_output=True
        )
        assert verified.returncode == 0, verified.stderr
        alive = await asyncio.to_thread(
            lambda: list(client.session.liveliness().get("touchshape/sim/alive", timeout=2.0))
        )
        assert alive and alive[0].ok
    finally:
        client.close()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (b"{not json", "not valid JSON"),
        (b"[1, 2]", "JSON object"),
        (json.dumps({"max_touches": 0}), "1..100"),
        (json.dumps({"max_touches": 101}), "1..100"),
        (json.dumps({"max_touches": "3"}), "integer"),
        (json.dumps({"policy": "greedy"}), "one of"),
        (json.dumps({"touches": 3}), "unknown key 'touches'"),
        ('{"max_touches": ' + "9" * 5000 + "}", "'max_touches' must be an integer in 1..100"),
        ('{"max_touches": 2, "max_touches": 3}', "duplicate key 'max_touches'"),
    ],
)
async def test_bad_requests_get_error_replies(served, body, message) -> None:
    service, client_config = served
    client = await asyncio.to_thread(Client, client_config)
    try:
        reply = (await client.aquery("explore", body))[0]
        assert reply["accepted"] is False and message in reply["error"]
        assert not service.busy
        assert (await client.aquery("status"))[0]["state"] == "idle"
    finally:
        client.close()


async def test_refused_requests_do_not_move_the_arm(served) -> None:
    """Unknown, path-like and huge prior names are refused before a session starts: no fault,
    no retreat, the TCP where it was, and a short reply."""
    service, client_config = served
    assert service.devices is not None
    before = (await service.devices.arm.state()).pose_base_tcp
    client = await asyncio.to_thread(Client, client_config)
    try:
        for body, field in [
            ({"prior": "nosuchprior"}, "'prior' must be one of 'auto', 'box', 'general'"),
            ({"prior": "../../etc/passwd"}, "'prior' must be a name"),
            ({"prior": "x" * 1_000_000}, "request is too large"),
            ({"prior": "x" * 10_000}, "'prior' must be a name"),
            ({"prior": "general", "max_touches": 0}, "'max_touches'"),
        ]:
            replies = await client.aquery("explore", json.dumps(body))
            assert len(replies) == 1 and replies[0]["accepted"] is False
            assert field in replies[0]["error"]
            assert len(json.dumps(replies[0])) < 300  # no echo of the input
        assert service.session is None and not service.busy
        after = (await service.devices.arm.state()).pose_base_tcp
        np.testing.assert_array_equal(after, before)
        assert not any(service.logs_dir.iterdir())  # no session folder, no recording
        # The service carries on: a valid request with a known prior runs.
        reply = (await client.aquery("explore", json.dumps({"prior": "box", "max_touches": 1})))[0]
        assert reply["accepted"] is True
        await wait_for(lambda: "result" in client.messages)
        assert client.messages["result"][0]["state"] == "done"
    finally:
        client.close()


async def test_taken_port_fails_before_devices_connect(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="controller.service")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    holder = await asyncio.to_thread(open_session, MessagingConfig(listen=(endpoint,)))
    try:
        config = dataclasses.replace(Config(), messaging=MessagingConfig(listen=(endpoint,)))
        service = TouchshapeService(config, make_cylinder_perception, logs_dir=tmp_path)
        with pytest.raises(EndpointError) as error:
            await service.serve(asyncio.Event())
        assert endpoint in str(error.value) and "\n" not in str(error.value)
        assert service.devices is None and service.perception is None
        assert "connecting the devices" not in caplog.text and "homing" not in caplog.text
    finally:
        await asyncio.to_thread(holder.close)


async def test_busy_and_idle_abort(served) -> None:
    _, client_config = served
    client = await asyncio.to_thread(Client, client_config)
    try:
        assert (await client.aquery("abort"))[0]["aborted"] is False
        first = (await client.aquery("explore", json.dumps({"max_touches": 3})))[0]
        second = (await client.aquery("explore"))[0]
        assert first["accepted"] and not second["accepted"] and "busy" in second["error"]
        aborted = (await client.aquery("abort"))[0]
        assert aborted == {"aborted": True, "session": first["session"]}
        await wait_for(lambda: "result" in client.messages)
        assert client.messages["result"][0]["state"] == "aborted"
        status = (await client.aquery("status"))[0]
        assert status["busy"] is False
        # Idle again: nothing is aborted, and the finished session is not named.
        assert (await client.aquery("abort"))[0] == {"aborted": False, "session": None}
    finally:
        client.close()


async def test_peer_without_credentials_cannot_trigger(tmp_path: Path) -> None:
    port = free_port()
    (tmp_path / "credentials.txt").write_text("operator:s3cret\n")
    (tmp_path / "password.txt").write_text("s3cret\n")
    secured = MessagingConfig(
        listen=(f"tcp/127.0.0.1:{port}",),
        user="operator",
        password_file=str(tmp_path / "password.txt"),
        credentials_file=str(tmp_path / "credentials.txt"),
    )
    config = dataclasses.replace(Config(), messaging=secured)
    service = TouchshapeService(config, make_cylinder_perception, logs_dir=tmp_path)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.serve(stop, ready))
    await asyncio.wait_for(ready.wait(), 60)
    try:
        intruder = await asyncio.to_thread(
            Client, MessagingConfig(listen=(), connect=(f"tcp/127.0.0.1:{port}",))
        )
        try:
            assert await intruder.aquery("explore", json.dumps({"max_touches": 1})) == []
        finally:
            intruder.close()
        assert not service.busy and service.session is None
        (tmp_path / "wrong.txt").write_text("guess\n")
        wrong = dataclasses.replace(
            secured,
            listen=(),
            connect=(f"tcp/127.0.0.1:{port}",),
            credentials_file="",
            password_file=str(tmp_path / "wrong.txt"),
        )
        impostor = await asyncio.to_thread(Client, wrong)
        try:
            assert await impostor.aquery("status") == []
        finally:
            impostor.close()
        operator = await asyncio.to_thread(
            Client,
            dataclasses.replace(
                secured, listen=(), connect=(f"tcp/127.0.0.1:{port}",), credentials_file=""
            ),
        )
        try:
            assert (await operator.aquery("status"))[0]["state"] == "idle"
        finally:
            operator.close()
    finally:
        stop.set()
        await task
