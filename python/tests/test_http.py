"""lsqsurfd --http-listen: the job page and its JSON API answer as the gRPC API does for the same
token (no second way to anyone's data), with the page's files embedded and the usual refusals."""
import json
import os
import ssl
import subprocess
import urllib.error
import urllib.request

import numpy as np
import pytest

import lsqsurf


def get(url, token=None, authorization=None, context=None):
    """(status, headers, body) of a GET."""
    request = urllib.request.Request(url)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    if authorization:
        request.add_header("Authorization", authorization)
    try:
        with urllib.request.urlopen(request, timeout=30, context=context) as response:
            return response.status, response.headers, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.headers, error.read()


@pytest.fixture(scope="module")
def alice_job(web_server):
    server, tokens = web_server
    rng = np.random.default_rng(2)
    points = rng.normal(size=(4000, 3))
    points /= np.linalg.norm(points, axis=1)[:, None]
    client = lsqsurf.Client(server.address, token=tokens["alice"])
    return client.wait(client.submit(points, method="iamls"))


def test_the_page_and_its_files(web_server, alice_job):
    server, _ = web_server
    status, headers, body = get(server.http + "/")
    assert status == 200 and headers["Content-Type"].startswith("text/html") and b"/static/app.js" in body
    assert "default-src 'self'" in headers["Content-Security-Policy"]
    assert headers["X-Content-Type-Options"] == "nosniff"
    assert get(f"{server.http}/jobs/{alice_job.id}")[2] == body  # the page routes itself
    status, headers, script = get(server.http + "/static/app.js")
    assert status == 200 and headers["Content-Type"].startswith("text/javascript")
    assert b"DRACOLoader" in script
    status, headers, wasm = get(server.http + "/static/draco/draco_decoder.wasm")
    assert status == 200 and headers["Content-Type"] == "application/wasm" and wasm[:4] == b"\0asm"
    status, _, three = get(server.http + "/static/OrbitControls.js")
    assert status == 200 and b"from './three.module.js'" in three and b"from 'three'" not in three
    status, _, missing = get(server.http + "/static/nothing.js")
    assert status == 404 and json.loads(missing)["code"] == "NOT_FOUND"
    assert get(server.http + "/static/../../etc/passwd")[0] == 404


def test_the_api_answers_for_the_token(web_server, alice_job):
    server, tokens = web_server
    status, headers, body = get(server.http + "/api/jobs")
    assert status == 401 and headers["WWW-Authenticate"] == "Bearer"
    assert json.loads(body)["code"] == "UNAUTHENTICATED"
    status, _, body = get(server.http + "/api/jobs", token=tokens["alice"])
    assert status == 200 and [j["id"] for j in json.loads(body)["jobs"]] == [alice_job.id]
    status, _, body = get(f"{server.http}/api/jobs/{alice_job.id}", token=tokens["alice"])
    job = json.loads(body)
    assert status == 200 and job["state"] == "JOB_STATE_SUCCEEDED" and "mesh.drc" in job["results"]
    # Bob sees nothing of alice's: her job is as missing to him as any other.
    assert json.loads(get(server.http + "/api/jobs", token=tokens["bob"])[2])["jobs"] == []
    status, _, body = get(f"{server.http}/api/jobs/{alice_job.id}", token=tokens["bob"])
    assert status == 404 and json.loads(body)["code"] == "NOT_FOUND"
    assert get(f"{server.http}/api/jobs/{alice_job.id}/results/mesh.drc", token=tokens["bob"])[0] == 404
    assert get(server.http + "/api/jobs", token="not-a-token")[0] == 401
    assert get(server.http + "/api/jobs", authorization="Basic YWxpY2U6eA==")[0] == 401
    assert get(server.http + "/api/jobs/zzz", token=tokens["alice"])[0] == 400
    status, _, body = get(server.http + "/api/methods", token=tokens["alice"])
    assert status == 200 and "pu" in [m["name"] for m in json.loads(body)["methods"]]


def test_results_download_as_over_grpc(web_server, alice_job):
    server, tokens = web_server
    status, headers, body = get(f"{server.http}/api/jobs/{alice_job.id}/results/mesh.drc", token=tokens["alice"])
    client = lsqsurf.Client(server.address, token=tokens["alice"])
    assert status == 200 and body == client.fetch(alice_job, "mesh.drc")
    assert int(headers["Content-Length"]) == len(body)
    status, _, body = get(f"{server.http}/api/jobs/{alice_job.id}/results/nothing.drc", token=tokens["alice"])
    assert status == 404 and "has no result" in json.loads(body)["message"]


def test_https_with_the_grpc_certificate(tls_server):
    server, certificate = tls_server
    assert server.http.startswith("https://")
    trusted = ssl.create_default_context(cafile=str(certificate))
    status, _, body = get(server.http + "/api/jobs", context=trusted)
    assert status == 200 and json.loads(body) == {"jobs": [], "next_page_token": ""}
    with pytest.raises(urllib.error.URLError):
        get(server.http + "/api/jobs")  # the system's roots do not know this certificate


def test_off_loopback_needs_tls_or_plaintext(tmp_path):
    binary = os.environ.get("LSQSURFD", "lsqsurfd")
    refused = subprocess.run([binary, "--listen", "127.0.0.1:0", "--http-listen", "0.0.0.0:0", "--data-dir",
                              str(tmp_path / "data")], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1 and "--http-listen 0.0.0.0:0 is not a loopback address" in refused.stderr
