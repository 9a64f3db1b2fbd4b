"""Servers the package's tests talk to: lsqsurfd ($LSQSURFD) started here on loopback, each with a
data folder of its own, stopped when the tests end."""
import os
import subprocess

import pytest


class Server:
    def __init__(self, folder, *extra):
        binary = os.environ.get("LSQSURFD", "lsqsurfd")
        self.process = subprocess.Popen(
            [binary, "--listen", "127.0.0.1:0", "--data-dir", str(folder / "data"), "--workers", "2", *extra],
            stdout=subprocess.PIPE, stderr=open(folder / "server.log", "wb"), text=True)
        line = self.process.stdout.readline()  # "listening on HOST:PORT" once it serves
        if not line.startswith("listening on "):
            self.process.kill()
            raise RuntimeError(f"lsqsurfd did not start: {(folder / 'server.log').read_text()[-2000:]}")
        self.address = line.split()[-1]
        self.http = None
        if "--http-listen" in extra:
            self.http = self.process.stdout.readline().split()[-1]  # "http on URL"

    def stop(self):
        self.process.terminate()
        self.process.wait(timeout=60)


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    started = Server(tmp_path_factory.mktemp("plain"))
    yield started
    started.stop()


def add_tokens(tokens, names):
    """Tokens for `names` in the token file `tokens` (lsqsurfd tokens add); returns {name: token}."""
    binary = os.environ.get("LSQSURFD", "lsqsurfd")
    return {name: subprocess.run([binary, "tokens", "add", str(tokens), name], capture_output=True, text=True,
                                 check=True).stdout.split()[-1] for name in names}


@pytest.fixture(scope="session")
def token_server(tmp_path_factory):
    """A server that asks every call for a token; yields (server, token)."""
    folder = tmp_path_factory.mktemp("tokens")
    token = add_tokens(folder / "tokens", ["alice"])["alice"]
    started = Server(folder, "--auth-tokens", str(folder / "tokens"))
    yield started, token
    started.stop()


@pytest.fixture(scope="session")
def web_server(tmp_path_factory):
    """A server with tokens for alice and bob and the job page; yields (server, {name: token})."""
    folder = tmp_path_factory.mktemp("web")
    names = add_tokens(folder / "tokens", ["alice", "bob"])
    started = Server(folder, "--auth-tokens", str(folder / "tokens"), "--http-listen", "127.0.0.1:0")
    yield started, names
    started.stop()


def make_certificate(folder):
    """A self-signed certificate for 127.0.0.1; returns (certificate, key) paths."""
    cert, key = folder / "server.pem", folder / "server.key"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
                    "-nodes", "-days", "2", "-subj", "/CN=lsqsurf test", "-addext",
                    "subjectAltName=IP:127.0.0.1,DNS:localhost", "-keyout", str(key), "-out", str(cert)],
                   check=True, capture_output=True)
    return cert, key


@pytest.fixture(scope="session")
def tls_server(tmp_path_factory):
    """A server that speaks TLS with a self-signed certificate for 127.0.0.1; yields (server,
    certificate path)."""
    folder = tmp_path_factory.mktemp("tls")
    cert, key = make_certificate(folder)
    started = Server(folder, "--tls-cert", str(cert), "--tls-key", str(key), "--http-listen", "127.0.0.1:0")
    yield started, cert
    started.stop()
