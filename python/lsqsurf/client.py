"""lsqsurf.Client: jobs on an lsqsurfd server from NumPy arrays."""
import csv
import io
import json
import os
import queue
import threading

import numpy as np

from . import _native, _params
from ._errors import JobFailed
from ._types import Cloud, Job, Mesh

DEFAULT_ADDRESS = "127.0.0.1:50051"
# VTK cell type codes by name, for Client.volume.
CELL_TYPES = {"tetra": 10, "hexahedron": 12, "wedge": 13, "pyramid": 14, "quadratic_tetra": 24, "quadratic_hexahedron": 25}


def read_cloud(path):
    """The point cloud in a file the CLI reads (PLY, PCD, LAS, PTS, PTX, XYZ, OBJ, Draco) as a
    Cloud, with its attributes and its sensors' positions. Raises ValueError for a file that
    cannot be read, naming it and what is wrong."""
    raw = _native.read_cloud(os.fspath(path))
    normals = raw["normals"] if len(raw["normals"]) else None
    return Cloud(raw["points"], normals, raw["attributes"], raw["sensors"], raw["shift"])


def _pem(value):
    """PEM text from PEM text, bytes or a file's path; "" for None."""
    if value is None:
        return ""
    if isinstance(value, bytes):
        return value.decode()
    text = str(value)
    if text.lstrip().startswith("-----BEGIN"):
        return text
    with open(text, encoding="ascii") as f:
        return f.read()


def _job_id(job):
    return job.id if isinstance(job, Job) else str(job)


def _points(array, what):
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{what} must be an N×3 array, got shape {array.shape}")
    return array


class Client:
    """A connection to an lsqsurfd server, set up as the CLI's flags and environment do.

    ``address`` defaults to $LSQSURF_SERVER, then 127.0.0.1:50051; ``token`` to $LSQSURF_TOKEN.
    ``tls_ca`` (certificates to trust; default the system's), ``tls_cert`` and ``tls_key`` (a
    client certificate, for mutual TLS) are PEM text or a file's path, defaulting to
    $LSQSURF_TLS_CA, $LSQSURF_TLS_CERT and $LSQSURF_TLS_KEY; ``server_name``
    ($LSQSURF_TLS_SERVER_NAME) overrides the name the server's certificate must carry. ``tls``:
    None (default) uses TLS for any server that is not on loopback or when a PEM is given; True
    always; False never (plaintext, e.g. behind a proxy that terminates TLS).

    Calls that wait release the GIL. A refused call raises RpcError (with the gRPC code); a job
    that fails raises JobFailed; a bad argument raises ValueError before anything is sent.
    """

    def __init__(self, address=None, *, token=None, tls=None, tls_ca=None, tls_cert=None, tls_key=None,
                 server_name=None):
        self.address = address or os.environ.get("LSQSURF_SERVER") or DEFAULT_ADDRESS
        if token is None:
            token = os.environ.get("LSQSURF_TOKEN", "")
        ca, cert, key = (_pem(given if given is not None else os.environ.get(env))
                         for given, env in ((tls_ca, "LSQSURF_TLS_CA"), (tls_cert, "LSQSURF_TLS_CERT"),
                                            (tls_key, "LSQSURF_TLS_KEY")))
        if bool(cert) != bool(key):
            raise ValueError("tls_cert and tls_key go together")
        if tls is False and (ca or cert):
            raise ValueError("tls=False contradicts the certificates given")
        if tls is None:
            tls = bool(ca or cert) or not _native.is_loopback(self.address)
        server_name = server_name or os.environ.get("LSQSURF_TLS_SERVER_NAME", "")
        self._connection = _native.Connection(self.address, token.strip(), bool(tls), ca, cert, key, server_name)
        self._methods = None

    # --- what the server offers -------------------------------------------------------------

    def methods(self):
        """The server's methods by name, each with its description and parameters (name, type,
        default, range, choices) as ListMethods reports them."""
        if self._methods is None:
            table = json.loads(self._connection.list_methods())
            self._methods = {m["name"]: m for m in table.get("methods", [])}
        return self._methods

    def server_info(self):
        """The server's version, limits and renderer (GetServerInfo) as a dict."""
        return json.loads(self._connection.server_info())

    # --- jobs -------------------------------------------------------------------------------

    def _spec(self, method, params, preview=None, mesh_bits=0):
        pairs = _params.check(self.methods(), method, params)
        spec = _native.Spec(method)
        for name, text in pairs:
            spec.set(name, text)
        for name, value in (preview or {}).items():
            spec.set_preview(name, _view_text(value))
        if mesh_bits:
            spec.set_mesh_bits(int(mesh_bits))
        return spec

    def submit(self, points=None, normals=None, *, method="pu", preview=None, mesh_bits=0, part_points=None,
               attributes=None, **params):
        """Uploads a point cloud (N×3, float32 or float64; ``normals`` N×3 or None; a Cloud as
        ``read_cloud`` gives, with its attributes and sensors) and returns the accepted Job
        without waiting. ``attributes`` maps names to one value per point (colour as "red",
        "green", "blue" in 0..255, "intensity", ...), carried to the mesh. ``params`` are the
        method's parameters (see ``methods()``); ``preview`` a dict of view options to draw
        preview.png with; ``mesh_bits`` the result's Draco position bits (0: chosen per mesh)."""
        if isinstance(points, Cloud):
            cloud = points
            points, normals = cloud.points, cloud.normals if normals is None else normals
            attributes = cloud.attributes if attributes is None else attributes
            if len(cloud.sensors) and "viewpoint" not in params:
                params["viewpoint"] = [float(v) for v in np.asarray(cloud.sensors).reshape(-1)]
        spec = self._spec(method, params, preview, mesh_bits)
        if points is None:
            return Job.from_json(self._connection.submit(spec, b"", b"", b""))
        points = _points(points, "points")
        if normals is not None and len(normals) == 0:
            normals = None
        if normals is not None:
            normals = _points(normals, "normals")
        per_part = int(part_points or _native.points_per_part)
        return Job.from_json(self._connection.submit_cloud(spec, points, normals, dict(attributes or {}), per_part))

    def watch(self, job):
        """The job's states as they change, as an iterator of Job, ending with its final state."""
        events = queue.Queue()
        end = object()

        def follow():
            try:
                self._connection.watch(_job_id(job), lambda text: events.put(Job.from_json(text)))
                events.put(end)
            except BaseException as error:  # noqa: BLE001 - handed to the consumer's thread
                events.put(error)

        # The watch runs on its own thread so that the caller's waits stay interruptible (Ctrl-C).
        threading.Thread(target=follow, daemon=True, name="lsqsurf-watch").start()
        while True:
            item = events.get()
            if item is end:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def wait(self, job, progress=None):
        """Follows the job to its end, calling ``progress(job)`` with each state; returns the
        final Job. Raises JobFailed when it did not succeed."""
        last = None
        for last in self.watch(job):
            if progress is not None:
                progress(last)
        if last is None:
            last = self.get(job)
        if last.state != "succeeded":
            raise JobFailed(last)
        return last

    def get(self, job):
        return Job.from_json(self._connection.get(_job_id(job)))

    def jobs(self, limit=100):
        """This user's jobs, newest first."""
        listing = json.loads(self._connection.list(int(limit)))
        return [Job.from_dict(j) for j in listing.get("jobs", [])]

    def cancel(self, job):
        return Job.from_json(self._connection.cancel(_job_id(job)))

    def delete(self, job):
        self._connection.delete(_job_id(job))

    def fetch(self, job, name=""):
        """A result's bytes (``name`` from ``job.results``; "" = the first)."""
        return self._connection.fetch(_job_id(job), name)

    def mesh(self, job):
        """A succeeded job's result mesh (mesh.drc, or the parts of a mesh delivered in parts)."""
        if not isinstance(job, Job):
            job = self.get(job)
        parts = [r for r in job.results if r.startswith("mesh-part-")]
        if not parts:
            decoded = _native.decode_mesh(self.fetch(job, "mesh.drc"))
            return Mesh(decoded["vertices"], decoded["faces"], decoded["normals"], decoded["attributes"], job)
        pieces = [_native.decode_mesh_part(self.fetch(job, name)) for name in sorted(parts)]
        attributes = {}
        for name in pieces[0]["attributes"]:
            attributes[name] = np.concatenate([p["attributes"][name] for p in pieces])
        normals = [p["normals"] for p in pieces]
        return Mesh(
            np.concatenate([p["vertices"] for p in pieces]),
            np.concatenate([p["faces"] for p in pieces]),
            np.concatenate(normals) if all(len(n) for n in normals) else None,
            attributes,
            job,
        )

    def reconstruct(self, points, normals=None, method="pu", progress=None, attributes=None, **params):
        """A surface through the points (an N×3 array, or a Cloud from ``read_cloud``): submits,
        waits (``progress(job)`` on each state) and returns the Mesh. Keyword parameters are the
        method's (``methods()[method]``)."""
        job = self.submit(points, normals, method=method, attributes=attributes, **params)
        return self.mesh(self.wait(job, progress))

    # --- the other kinds of job -------------------------------------------------------------

    def csg(self, expression, progress=None, **params):
        """A solid from primitives and kept pu results (see the README's CSG syntax) as a Mesh."""
        job = self.submit(method="csg", expression=expression, **params)
        return self.mesh(self.wait(job, progress))

    def edit(self, job, ball, *, set_degree=None, refit=None, remove=False, progress=None, **params):
        """A local edit of a kept pu function in ``ball`` = (x, y, z, r): give one of
        ``set_degree=N``, ``refit=error_threshold`` or ``remove=True``. Returns the edited Mesh."""
        if (set_degree is not None) + (refit is not None) + bool(remove) != 1:
            raise ValueError("give one of set_degree=N, refit=E or remove=True")
        x, y, z, r = (float(v) for v in ball)
        if remove:
            action = {"action": "remove"}
        elif set_degree is not None:
            action = {"action": "set_degree", "degree": set_degree}
        else:
            action = {"action": "refit", "error_threshold": refit}
        edited = self.submit(method="edit", source=_job_id(job), center_x=x, center_y=y, center_z=z, radius=r,
                             **action, **params)
        return self.mesh(self.wait(edited, progress))

    def volume(self, points, cells=None, cell_types=10, fields=None, *, field=None, iso=(), progress=None,
               **params):
        """A scalar field reconstructed on a volume mesh (or a point set when ``cells`` is None).

        ``cells``: an M×K array of corner indices (every cell of one type) or a list of index
        sequences; ``cell_types``: one VTK code (10 tetrahedron, 12 hexahedron, 13 wedge, 14
        pyramid, 24/25 quadratic) or one per cell; ``fields``: name -> one value per point (NaN
        marks a missing value); ``field``: the one to reconstruct (default the first); ``iso``:
        isosurface levels. Returns the finished Job: ``mesh(job)`` has the isosurfaces, and
        ``probe`` and ``render`` take the job."""
        points = _points(points, "points")
        fields = dict(fields or {})
        if not fields:
            raise ValueError("give at least one field: fields={'name': values}")
        corners, offsets, types = _cell_arrays(cells, cell_types)
        vertices, cell_stream, _ = _native.encode_volume(points, corners, offsets, types, fields)
        spec = self._spec("volume", dict(params, field=field or next(iter(fields)), iso=list(iso) or None))
        job = Job.from_json(self._connection.submit(spec, vertices, b"", cell_stream))
        return self.wait(job, progress)

    def probe(self, job, points, field=None):
        """The field of a succeeded volume job at the points: (values, gradients), N and N×3
        float64, NaN where a point lies outside the data."""
        points = _points(points, "points")
        spec = self._spec("probe", {"source": _job_id(job), "field": field})
        probe = self.wait(Job.from_json(self._connection.submit(spec, _native.encode_cloud(points, None, True), b"", b"")))
        rows = list(csv.reader(io.StringIO(self.fetch(probe, "values.csv").decode())))[1:]
        values = np.full(len(points), np.nan)
        gradients = np.full((len(points), 3), np.nan)
        for i, row in enumerate(rows):
            if len(row) >= 7 and row[3] != "":
                values[i] = float(row[3])
                gradients[i] = [float(v) for v in row[4:7]]
        self.delete(probe)
        return values, gradients

    def render(self, job, name="", *, size=None, **view):
        """A PNG picture of a result (``name`` from ``job.results``; "" = the first). ``size`` is
        an int (square) or (width, height); other keywords are view options (``azimuth_deg``,
        ``elevation_deg``, ``up_axis``, ``color``, ``samples``, ... as in the README)."""
        if size is not None:
            width, height = (size, size) if isinstance(size, int) else size
            view = dict(view, width=width, height=height)
        options = [(key, _view_text(value)) for key, value in view.items() if value is not None]
        png, _ = self._connection.render(_job_id(job), name, options)
        return png

    def track(self, points=None, normals=None, *, velocity=None, progress=None, **params):
        """Front tracking: advects an interface (the built-in ``interface="sphere"`` or
        ``"zalesak"``, or the uploaded oriented cloud ``points``/``normals``) through a field (built
        in, or ``velocity``: legacy VTK bytes). Returns the finished Job; ``fetch`` its frames."""
        if points is not None:
            params.setdefault("interface", "uploaded")
        if velocity is not None:
            params.setdefault("field", "uploaded")
        spec = self._spec("track", params)
        cloud = b""
        if points is not None:
            if normals is None:
                raise ValueError("an uploaded interface needs its outward normals")
            cloud = _native.encode_cloud(_points(points, "points"), _points(normals, "normals"), False)
        job = Job.from_json(self._connection.submit(spec, cloud, bytes(velocity or b""), b""))
        return self.wait(job, progress)


def _view_text(value):
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(float(value)) if isinstance(value, float) else str(value)


def _cell_arrays(cells, cell_types):
    """Flat corner indices, offsets and one type per cell."""
    if cells is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    if isinstance(cells, np.ndarray) and cells.ndim == 2:
        counts = np.full(len(cells), cells.shape[1], np.int64)
        corners = cells.astype(np.int64).reshape(-1)
    else:
        rows = [np.asarray(c, np.int64).reshape(-1) for c in cells]
        counts = np.array([len(r) for r in rows], np.int64)
        corners = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    if isinstance(cell_types, str):
        cell_types = CELL_TYPES[cell_types]
    types = np.broadcast_to(np.asarray(cell_types, np.int64), counts.shape).copy()
    return corners, offsets, types
