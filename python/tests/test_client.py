"""The Python package against a real server: NumPy in, meshes and fields out, checked against
analytic truth; bad arguments refused before anything is sent; server errors with their code."""
import struct

import numpy as np
import pytest

import lsqsurf


def sphere_cloud(n, radius=0.5, seed=7):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1)[:, None]
    return p * radius, p.copy()


@pytest.fixture(scope="module")
def client(server):
    return lsqsurf.Client(server.address)


@pytest.mark.parametrize("method", ["iamls", "pu"])
def test_reconstruct_gives_a_closed_sphere(client, method):
    points, _ = sphere_cloud(20000)
    events = []
    mesh = client.reconstruct(points.astype(np.float32), method=method, progress=events.append)
    assert mesh.is_closed()
    radii = np.linalg.norm(mesh.vertices, axis=1)
    assert np.max(np.abs(radii - 0.5)) < 0.005
    assert mesh.faces.shape[1] == 3 and mesh.faces.max() < len(mesh.vertices)
    assert mesh.job.state == "succeeded" and mesh.job.method == method
    assert mesh.statistics["triangles"] == len(mesh.faces)
    assert events and events[-1].state == "succeeded"
    # Normals point outwards, as the mesh's orientation does.
    assert np.mean(np.sum(mesh.normals * mesh.vertices, axis=1) > 0) > 0.99


def test_parameters_reach_the_job(client):
    points, normals = sphere_cloud(5000)
    mesh = client.reconstruct(points, normals, method="pu", max_degree=2, sharp=False, cell_size=4.0)
    pu = mesh.job.spec["pu"]
    assert pu["max_degree"] == 2 and pu["sharp"] is False and pu["cell_size"] == 4.0
    assert mesh.job.statistics.get("estimated_normals", 0) == 0 or "normals" not in mesh.job.statistics


@pytest.mark.parametrize(
    "params, named",
    [
        ({"degre": 2}, "'degre'"),                  # unknown
        ({"cell_size": 1000.0}, "'cell_size'"),     # out of range
        ({"max_degree": 1.5}, "'max_degree'"),      # not whole
        ({"sharp": "yes"}, "'sharp'"),              # not a flag
        ({"support_factor": float("nan")}, "'support_factor'"),
    ],
)
def test_bad_keywords_raise_before_any_upload(client, params, named):
    before = len(client.jobs(limit=1000))
    with pytest.raises(ValueError, match=named):
        client.reconstruct(np.zeros((100, 3)), method="pu", **params)
    assert len(client.jobs(limit=1000)) == before


def test_bad_arrays_and_methods_raise_value_error(client):
    with pytest.raises(ValueError, match="N×3"):
        client.submit(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="not finite"):
        client.submit(np.full((100, 3), np.nan))
    with pytest.raises(ValueError, match="unknown method 'poisson'"):
        client.submit(np.zeros((100, 3)), method="poisson")
    with pytest.raises(ValueError, match="extractor"):
        client.submit(np.zeros((100, 3)), method="iamls", extractor="marching")


def test_server_errors_carry_the_grpc_code(client):
    with pytest.raises(lsqsurf.RpcError) as missing:
        client.get("0" * 32)
    assert missing.value.code == 5 and missing.value.code_name == "NOT_FOUND"
    with pytest.raises(lsqsurf.RpcError) as malformed:
        client.fetch("not-an-id")
    assert malformed.value.code == 3
    # Too few points for any surface: the server refuses the upload itself.
    with pytest.raises(lsqsurf.RpcError) as few:
        client.submit(np.random.default_rng(1).random((5, 3)))
    assert few.value.code_name == "INVALID_ARGUMENT" and "points" in few.value.details


@pytest.fixture(scope="module")
def kept_sphere(client):
    """A pu sphere of radius 0.5 whose function the server keeps, for edits."""
    points, normals = sphere_cloud(10000)
    return client.reconstruct(points, normals, method="pu", keep_function=True)


def test_a_failed_job_raises_job_failed(client, kept_sphere):
    # A ball far from every fit: accepted, then the job fails saying why.
    with pytest.raises(lsqsurf.JobFailed) as failed:
        client.edit(kept_sphere.job, (5.0, 5.0, 5.0, 0.1), set_degree=2)
    assert failed.value.job.state == "failed" and failed.value.job.error


def test_submit_watch_fetch_and_delete(client):
    points, _ = sphere_cloud(8000)
    job = client.submit(points, method="iamls")
    states = [j.state for j in client.watch(job)]
    assert states[-1] == "succeeded" and all(s in ("queued", "running", "succeeded") for s in states)
    assert client.get(job).results[0] == "mesh.drc"
    assert client.fetch(job)[:5] == b"DRACO"
    assert job.id in [j.id for j in client.jobs()]
    client.delete(job)
    with pytest.raises(lsqsurf.RpcError):
        client.get(job)


def png_size(data):
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_render_gives_the_picture_asked_for(client):
    points, _ = sphere_cloud(5000)
    job = client.wait(client.submit(points, method="iamls"))
    assert png_size(client.render(job, size=(96, 64))) == (96, 64)
    one, four = client.render(job, size=64, samples=1), client.render(job, size=64, samples=4)
    assert one != four
    with pytest.raises(ValueError, match="no field 'zoom'"):
        client.render(job, zoom=2)
    with pytest.raises(lsqsurf.RpcError) as refused:
        client.render(job, size=5)
    assert refused.value.code_name == "INVALID_ARGUMENT"


def test_a_job_draws_its_own_preview(client):
    points, _ = sphere_cloud(4000)
    job = client.wait(client.submit(points, method="iamls", preview={"width": 80, "height": 60}, mesh_bits=20))
    assert "preview.png" in job.results
    assert png_size(client.fetch(job, "preview.png")) == (80, 60)
    assert job.statistics["delivered_position_bits"] == 20
    with pytest.raises(ValueError, match="no field 'zoom'"):
        client.submit(points, preview={"zoom": 2})


def cube_grid(n):
    """An n³-vertex grid over the unit cube, each cube cut into six tetrahedra."""
    axis = np.linspace(0.0, 1.0, n)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    index = np.arange(n ** 3).reshape(n, n, n)
    c = [index[i:n - 1 + i, j:n - 1 + j, k:n - 1 + k].ravel() for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    # Corners c[ijk] with i, j, k the offsets; six tetrahedra along the main diagonal 000-111.
    paths = [(4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)]
    tets = [np.stack([c[0], c[a], c[b], c[7]], axis=1) for a, b in paths]
    return points, np.concatenate(tets)


def test_volume_field_isosurface_and_probe(client):
    points, tets = cube_grid(9)
    value = points @ np.array([1.0, 2.0, -1.0])  # linear: its gradient is exact everywhere
    job = client.volume(points, tets, "tetra", {"f": value}, iso=[0.5, 1.0])
    assert job.state == "succeeded" and job.method == "volume"
    surface = client.mesh(job)
    assert len(surface.faces) > 0
    # Two levels: each vertex carries its level as the scalar "iso", in the order the method's
    # table names its scalars (the job page reads them by position), and lies on that plane.
    assert list(surface.attributes) == client.methods()["volume"]["attributes"] == ["iso"]
    level = surface.attributes["iso"]
    assert set(np.unique(np.round(level, 3))) == {0.5, 1.0}
    assert np.max(np.abs(surface.vertices @ np.array([1.0, 2.0, -1.0]) - level)) < 1e-3
    rng = np.random.default_rng(3)
    inside = rng.uniform(0.1, 0.9, size=(50, 3))
    outside = np.array([[3.0, 3.0, 3.0]])
    values, gradients = client.probe(job, np.concatenate([inside, outside]))
    assert np.max(np.abs(values[:50] - inside @ np.array([1.0, 2.0, -1.0]))) < 1e-3
    assert np.max(np.abs(gradients[:50] - [1.0, 2.0, -1.0])) < 1e-2
    assert np.isnan(values[50]) and np.all(np.isnan(gradients[50]))
    assert png_size(client.render(job, "field.lqvf", size=48)) == (48, 48)


def test_volume_refuses_bad_cells_before_upload(client):
    points, tets = cube_grid(3)
    tets[0, 0] = len(points)
    with pytest.raises(ValueError, match="not one of the 27 points"):
        client.volume(points, tets, "tetra", {"f": points[:, 0]})
    with pytest.raises(ValueError, match="one number per point"):
        client.volume(points, tets[1:], "tetra", {"f": points[:5, 0]})


def test_csg_and_edit(client, kept_sphere):
    sphere = client.csg("sphere(c=0,0,0 r=0.3)")
    assert sphere.is_closed()
    assert np.max(np.abs(np.linalg.norm(sphere.vertices, axis=1) - 0.3)) < 0.003
    kept = kept_sphere
    holed = client.edit(kept.job, (0.5, 0.0, 0.0, 0.1), remove=True)
    assert not holed.is_closed()  # the ball cut a hole
    assert np.min(np.linalg.norm(holed.vertices - [0.5, 0, 0], axis=1)) > 0.05
    with pytest.raises(ValueError, match="one of"):
        client.edit(kept.job, (0, 0, 0, 0.1))


def test_track_a_built_in_interface(client):
    job = client.track(interface="sphere", field="rotation", cells=32, steps=4, stride=2, dt=0.5)
    frames = [r for r in job.results if r.startswith("frame_") and r.endswith(".drc")]
    assert len(frames) >= 2


def test_tokens(token_server, monkeypatch):
    server, token = token_server
    with pytest.raises(lsqsurf.RpcError) as refused:
        lsqsurf.Client(server.address, token="").jobs()
    assert refused.value.code_name == "UNAUTHENTICATED"
    assert lsqsurf.Client(server.address, token=token).jobs() == []
    monkeypatch.setenv("LSQSURF_SERVER", server.address)
    monkeypatch.setenv("LSQSURF_TOKEN", token)
    assert lsqsurf.Client().jobs() == []
    with pytest.raises(ValueError, match="token"):
        lsqsurf.Client(server.address, token="two words")



def test_tls(tls_server):
    server, certificate = tls_server
    assert lsqsurf.Client(server.address, tls_ca=certificate).jobs() == []
    assert lsqsurf.Client(server.address, tls_ca=certificate.read_text()).jobs() == []
    with pytest.raises(lsqsurf.RpcError) as plain:
        lsqsurf.Client(server.address, tls=False).jobs()
    assert plain.value.code_name == "UNAVAILABLE"
    with pytest.raises(ValueError, match="go together"):
        lsqsurf.Client(server.address, tls_cert=certificate)


DATA = __import__("pathlib").Path(__file__).resolve().parents[2] / "tests" / "data"


def test_read_cloud_gives_a_files_points_colours_and_sensor():
    # An RGB-D view PCL wrote (binary_compressed, packed colour, a VIEWPOINT).
    milk = lsqsurf.read_cloud(DATA / "pcd" / "milk_color.pcd")
    assert milk.points.shape == (13704, 3) and len(milk.normals) == 0
    assert milk.colors.shape == (13704, 3) and milk.colors.dtype == np.uint8
    assert milk.sensors.shape == (1, 3)
    # A georeferenced LAS file: moved by whole units near the origin, and the shift said.
    utm = lsqsurf.read_cloud(DATA / "las" / "utm_1_2_format1.las")
    assert utm.shift[0] == 500012.0 and utm.shift[1] == 4000002.0
    assert np.max(np.abs(utm.points[:, :2])) < 20
    assert set(utm.attributes) == {"intensity", "classification"} and utm.colors is None
    with pytest.raises(ValueError, match="unsupported file type"):
        lsqsurf.read_cloud(DATA / "las" / "make_las.py")


def test_a_coloured_clouds_mesh_keeps_its_colours(client):
    points, normals = sphere_cloud(20000)
    # Red where x > 0, blue elsewhere: each vertex takes its side's colour.
    red = np.where(points[:, 0] > 0, 250.0, 10.0)
    cloud = lsqsurf.Cloud(points, normals, {"red": red, "green": np.full(len(points), 60.0), "blue": 260.0 - red})
    mesh = client.reconstruct(cloud, method="iamls")
    assert mesh.colors is not None and mesh.colors.shape == (len(mesh.vertices), 3)
    away = np.abs(mesh.vertices[:, 0]) > 0.05
    expected = np.where(mesh.vertices[away, 0] > 0, 250, 10)
    assert np.max(np.abs(mesh.colors[away, 0].astype(int) - expected)) <= 2
    assert np.all(mesh.colors[:, 1] == 60)
