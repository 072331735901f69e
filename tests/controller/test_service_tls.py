"""The service over Zenoh with TLS on loopback: a client trusting the service's CA is answered;
one that does not, or that speaks plain TCP, is not; with mutual TLS a client needs its own
certificate. Certificates are made for the test with the ``openssl`` command line tool."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import shutil
import subprocess
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from controller.config import Config, MessagingConfig
from controller.service import TouchshapeService
from tests.fakes.perception import make_cylinder_perception
from tests.fakes.zenoh_client import Client, free_port

pytestmark = pytest.mark.skipif(
    shutil.which("openssl") is None, reason="the openssl command is needed to make certificates"
)


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def make_certificates(folder: Path) -> dict[str, Path]:
    """A throw-away CA, a service certificate for localhost signed by it, and a client
    certificate signed by it (for mutual TLS)."""
    _openssl(
        "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
        "-keyout", "ca-key.pem", "-out", "ca.pem", "-subj", "/CN=touchshape test CA",
        "-addext", "basicConstraints=critical,CA:TRUE",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        cwd=folder,
    )  # fmt: skip
    for name, usage in (("service", "serverAuth"), ("client", "clientAuth")):
        _openssl(
            "req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}-key.pem",
            "-out", f"{name}.csr", "-subj", f"/CN={name}",
            cwd=folder,
        )  # fmt: skip
        (folder / f"{name}.ext").write_text(
            "basicConstraints=CA:FALSE\n"
            "subjectAltName=DNS:localhost,IP:127.0.0.1\n"
            f"extendedKeyUsage={usage}\n"
        )
        _openssl(
            "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem",
            "-CAcreateserial", "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext",
            cwd=folder,
        )  # fmt: skip
    return {name: folder / f"{name}.pem" for name in ("ca", "service", "client")} | {
        f"{name}_key": folder / f"{name}-key.pem" for name in ("service", "client")
    }


@contextlib.asynccontextmanager
async def serve(tmp_path: Path, messaging: MessagingConfig) -> AsyncIterator[TouchshapeService]:
    config = dataclasses.replace(
        Config(),
        sim=dataclasses.replace(Config().sim, object="can"),
        messaging=messaging,
    )
    service = TouchshapeService(config, make_cylinder_perception, logs_dir=tmp_path)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.serve(stop, ready))
    await asyncio.wait_for(ready.wait(), 60)
    try:
        yield service
    finally:
        stop.set()
        await task


async def status_replies(messaging: MessagingConfig) -> list[dict]:
    client = await asyncio.to_thread(Client, messaging)
    try:
        return await client.aquery("status")
    finally:
        await asyncio.to_thread(client.close)


@pytest.fixture
def certificates(tmp_path: Path) -> dict[str, Path]:
    folder = tmp_path / "tls"
    folder.mkdir()
    return make_certificates(folder)


async def test_service_answers_over_tls(tmp_path: Path, certificates: dict[str, Path]) -> None:
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    served = MessagingConfig(
        listen=(endpoint,),
        tls_certificate=str(certificates["service"]),
        tls_private_key=str(certificates["service_key"]),
    )
    trusting = MessagingConfig(
        listen=(), connect=(endpoint,), tls_root_ca_certificate=str(certificates["ca"])
    )
    async with serve(tmp_path, served):
        assert (await status_replies(trusting))[0]["state"] == "idle"
        # A client that does not trust the service's CA (its own CA instead) gets nothing,
        # and neither does one speaking plain TCP to the TLS port.
        other_ca = tmp_path / "other"
        other_ca.mkdir()
        stranger = dataclasses.replace(
            trusting, tls_root_ca_certificate=str(make_certificates(other_ca)["ca"])
        )
        assert await status_replies(stranger) == []
        plain = MessagingConfig(listen=(), connect=(f"tcp/localhost:{port}",))
        assert await status_replies(plain) == []


async def test_mutual_tls_needs_a_client_certificate(
    tmp_path: Path, certificates: dict[str, Path]
) -> None:
    port = free_port()
    endpoint = f"tls/localhost:{port}"
    served = MessagingConfig(
        listen=(endpoint,),
        tls_root_ca_certificate=str(certificates["ca"]),
        tls_certificate=str(certificates["service"]),
        tls_private_key=str(certificates["service_key"]),
        tls_mutual=True,
    )
    without_certificate = MessagingConfig(
        listen=(), connect=(endpoint,), tls_root_ca_certificate=str(certificates["ca"])
    )
    with_certificate = dataclasses.replace(
        without_certificate,
        tls_certificate=str(certificates["client"]),
        tls_private_key=str(certificates["client_key"]),
        tls_mutual=True,
    )
    async with serve(tmp_path, served):
        assert await status_replies(without_certificate) == []
        assert (await status_replies(with_certificate))[0]["state"] == "idle"
