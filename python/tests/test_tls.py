"""https:// URLs: TLS with a trusted CA file (a self-signed certificate made with openssl)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

import blapose
from conftest import EXAMPLES


@pytest.fixture
def cert(tmp_path: Path):
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed")
    key, crt = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", str(key), "-out", str(crt), "-days", "1", "-subj", "/CN=localhost",
         "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    return crt, key


def test_tls_with_ca_cert_and_token(start_server, cert) -> None:
    crt, key = cert
    srv = start_server("--tls-cert", str(crt), "--tls-key", str(key), "--auth-token", "t0k")
    url = f"https://localhost:{srv.port}"
    seq = blapose.load_replay(EXAMPLES[0])
    with blapose.Client(url, token="t0k", ca_cert=crt) as client:
        assert client.info().protocol == "blapose.v1"
        with client.session(layout=seq.layout, image_size=seq.image_size) as s:
            assert len(list(s.stream(seq.frames()))) == seq.num_frames
    with blapose.Client(url, ca_cert=crt.read_bytes()) as client, pytest.raises(blapose.Unauthenticated):
        client.info()
    # Plaintext against a TLS server, and TLS without trusting the certificate, both fail.
    with blapose.Client(f"http://localhost:{srv.port}", token="t0k", timeout=3) as client:
        with pytest.raises(blapose.RpcError):
            client.info()
    with blapose.Client(url, token="t0k", timeout=3) as client, pytest.raises(blapose.Unavailable):
        client.info()
