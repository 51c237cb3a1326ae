"""TLS: `isosr serve --tls-cert/--tls-key` serves HTTPS and WSS (a self-signed certificate made
here, a real uvicorn on loopback); the Python client trusts it through ``cafile``; serving beyond
loopback needs TLS unless ``--insecure``; bad certificate and key files are one-line errors
naming the file."""

from __future__ import annotations

import ssl
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from isosr_cli.main import main
from isosr_client import connect, upscale_remote
from isosr_client.view import ServerError
from isosr_render import orbit
from isosr_server.core.config import Settings
from server_fixtures import (VOLUME, H, W, lib, lib_full, lib_lowres, running_server, self_signed_cert,  # noqa: F401
                             server_settings, write_key)

TOKEN = "tls-test-token"
PNG = {"encoding": "png", "refine": False}


@pytest.fixture(scope="module")
def cert(tmp_path_factory) -> tuple[Path, Path]:
    return self_signed_cert(tmp_path_factory.mktemp("tls"))


def test_bad_certificate_and_key_files_name_the_file(cert, tmp_path):
    crt, key = cert
    other = tmp_path / "other.pem"
    write_key(other)
    cases = [(tmp_path / "none.pem", key, f"--tls-cert {tmp_path / 'none.pem'}: No such file"),
             (crt, tmp_path / "none.pem", f"--tls-key {tmp_path / 'none.pem'}: No such file"),
             (tmp_path, key, f"--tls-cert {tmp_path}: Is a directory"),
             (key, key, f"--tls-cert {key}: no PEM certificate in it"),
             (crt, crt, f"--tls-key {crt}: not the unencrypted PEM private key of {crt}"),
             (crt, other, f"--tls-key {other}: not the unencrypted PEM private key of {crt}")]
    for c, k, words in cases:
        with pytest.raises(ValueError) as e:
            Settings(tls_cert=c, tls_key=k)
        assert str(e.value).startswith(words) and "\n" not in str(e.value), e.value
    with pytest.raises(ValueError, match="--tls-cert and --tls-key go together"):
        Settings(tls_cert=crt)
    settings = Settings(tls_cert=crt, tls_key=key)
    assert settings.scheme == "https" and settings.tls_options() == {"ssl_certfile": str(crt), "ssl_keyfile": str(key)}
    assert Settings().scheme == "http" and Settings().tls_options() == {}


def test_beyond_loopback_needs_a_token_and_tls_unless_insecure(cert):
    crt, key = cert
    with pytest.raises(ValueError, match=r"WebCodecs needs HTTPS\): give --tls-cert and --tls-key, or --insecure"):
        Settings(host="0.0.0.0", token=TOKEN)
    with pytest.raises(ValueError, match="--token"):  # TLS does not stand in for the token
        Settings(host="0.0.0.0", tls_cert=crt, tls_key=key)
    assert Settings(host="0.0.0.0", token=TOKEN, tls_cert=crt, tls_key=key).scheme == "https"
    assert Settings(host="0.0.0.0", token=TOKEN, insecure=True).scheme == "http"
    assert Settings(host="127.0.0.1").scheme == "http"  # loopback: neither needed
    env = {"ISOSR_HOST": "0.0.0.0", "ISOSR_TOKEN": TOKEN}
    assert Settings.from_env(env | {"ISOSR_INSECURE": "yes"}).insecure
    assert Settings.from_env(env | {"ISOSR_TLS_CERT": str(crt), "ISOSR_TLS_KEY": str(key)}).tls_cert == crt
    with pytest.raises(ValueError, match="WebCodecs"):
        Settings.from_env(env | {"ISOSR_INSECURE": "0"})
    with pytest.raises(ValueError, match="ISOSR_INSECURE='maybe' is not a valid insecure"):
        Settings.from_env(env | {"ISOSR_INSECURE": "maybe"})


def test_serve_command_refuses_plain_http_beyond_loopback_in_one_line(capsys, monkeypatch, tmp_path):
    monkeypatch.delenv("ISOSR_INSECURE", raising=False)
    assert main(["serve", "--host", "0.0.0.0", "--token", TOKEN]) == 2
    err = capsys.readouterr().err.strip()
    assert "--insecure" in err and "WebCodecs" in err and len(err.splitlines()) == 1
    missing = tmp_path / "missing.pem"
    assert main(["serve", "--tls-cert", str(missing), "--tls-key", str(missing)]) == 2
    assert f"--tls-cert {missing}: No such file" in capsys.readouterr().err


def test_client_over_https_and_wss_with_a_cafile(cert, lib):  # noqa: F811
    crt, key = cert
    camera = orbit(30, 20, 1.8)
    with running_server(server_settings(tls_cert=crt, tls_key=key)) as s:
        assert s.http_url.startswith("https://") and s.ws_url.startswith("wss://")
        with connect(s.http_url, VOLUME, "full", (W, H), settings=PNG, cafile=crt,
                     camera={"yaw": 30.0, "pitch": 20.0, "distance": 1.8}) as view:
            assert (view.frame() == lib_full(lib, camera)).all()  # png over wss: the library's frame
        assert upscale_remote(s.http_url, lib_lowres(lib, camera), cafile=crt).buffers.ao.shape == (H, W)
        with urllib.request.urlopen(s.http_url + "/v2/health/ready",
                                    context=ssl.create_default_context(cafile=crt)) as health:
            assert health.status == 200
        # Not trusted: the system's authorities do not know the self-signed certificate.
        with pytest.raises(ConnectionError, match="CERTIFICATE_VERIFY_FAILED"):
            connect(s.http_url, VOLUME, "full", (W, H), settings=PNG)
        with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
            upscale_remote(s.http_url, lib_lowres(lib, camera))
        # Plain HTTP to the TLS port gets no session.
        with pytest.raises((ConnectionError, ServerError)):
            connect(s.http_url.replace("https", "http"), VOLUME, "full", (W, H), settings=PNG, timeout=10)
    with pytest.raises(ValueError, match="goes with an https or wss URL"):
        connect("http://127.0.0.1:1", VOLUME, cafile=crt)
    with pytest.raises(ValueError, match=f"cafile {key}: no PEM certificate in it"):
        upscale_remote("https://127.0.0.1:1", lib_lowres(lib, camera), cafile=key)
