"""TLS and the bearer token together, against a server with a self-signed certificate."""

from __future__ import annotations

import subprocess
from pathlib import Path

import grpc
import pytest

import esrp


def self_signed(folder: Path) -> tuple[Path, Path]:
    """A certificate for localhost and 127.0.0.1, and its key (openssl, as Debian ships it)."""
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(
        [
            "openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-days", "2", "-subj", "/CN=localhost",
            "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1",
            "-keyout", str(key), "-out", str(cert),
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    return cert, key


def test_tls_and_token(tmp_path: Path) -> None:
    cert, key = self_signed(tmp_path)
    args = ("--tls-cert", str(cert), "--tls-key", str(key), "--token", "s3cret")
    with esrp.LocalServer(*args) as server:
        port = server.address.rsplit(":", 1)[1]
        for tls in (cert.read_bytes(), cert, grpc.ssl_channel_credentials(cert.read_bytes())):
            with esrp.Client(f"localhost:{port}", tls=tls, token="s3cret", timeout=30) as client:
                client.wait_healthy()
                assert client.server_info().dataset == "esrp-bench-v2"
                with client.create_episode(split="test") as episode:
                    assert episode.step(esrp.Action.LEFT).info.step_index == 1
        # https:// with the name checked against the certificate's, not the address's.
        with esrp.Client(
            f"https://127.0.0.1:{port}", tls=cert.read_bytes(), tls_server_name="localhost", token="s3cret"
        ) as client:
            assert client.server_info().live_episodes == 0
        with (
            esrp.Client(f"localhost:{port}", tls=cert, timeout=30) as anonymous,
            pytest.raises(esrp.Unauthenticated),
        ):
            anonymous.server_info()
        # A plain-text client cannot talk to a TLS port.
        with (
            esrp.Client(server.address, token="s3cret", timeout=30) as plain,
            pytest.raises(esrp.ServerUnavailable),
        ):
            plain.server_info()
