"""What the client hands back: jobs and meshes."""
import json
from dataclasses import dataclass, field

import numpy as np

_TERMINAL = ("succeeded", "failed", "cancelled")


def _state_name(state):
    # "JOB_STATE_SUCCEEDED" -> "succeeded", as the CLI prints it.
    return state.removeprefix("JOB_STATE_").lower()


@dataclass(frozen=True)
class Job:
    """A job as the server last reported it.

    ``state`` is one of queued, running, succeeded, failed, cancelled; ``progress`` is in [0, 1];
    ``statistics`` maps each statistic's name to its value (final once the job succeeded);
    ``results`` names what ``Client.fetch`` can download; ``spec`` is the job's parameters as run
    (JSON form of ``lsqsurf.v1.JobSpec``).
    """

    id: str
    state: str
    stage: str
    progress: float
    error: str
    method: str
    statistics: dict = field(repr=False)
    results: list = field(repr=False)
    input_points: int = 0
    created_ms: int = 0
    updated_ms: int = 0
    owner: str = ""
    spec: dict = field(default_factory=dict, repr=False)

    @property
    def done(self):
        """True once the job has ended (succeeded, failed or cancelled)."""
        return self.state in _TERMINAL

    @classmethod
    def from_json(cls, text):
        return cls.from_dict(json.loads(text))

    @classmethod
    def from_dict(cls, raw):
        spec = raw.get("spec", {})
        method = next((k for k, v in spec.items() if isinstance(v, dict) and k != "preview"), "")
        return cls(
            id=raw["id"],
            state=_state_name(raw["state"]),
            stage=raw.get("stage", ""),
            progress=float(raw.get("progress", 0.0)),
            error=raw.get("error", ""),
            method=method,
            statistics={s["name"]: s["value"] for s in raw.get("statistics", [])},
            results=list(raw.get("results", [])),
            input_points=int(raw.get("input_points", 0)),
            created_ms=int(raw.get("created_ms", 0)),
            updated_ms=int(raw.get("updated_ms", 0)),
            owner=raw.get("owner", ""),
            spec=spec,
        )


class Cloud:
    """A point cloud as a file holds it (``read_cloud``): ``points`` (N×3 float32), ``normals``
    (N×3, or 0×3 when the file has none), ``attributes`` (name -> one float32 per point: colour
    as "red", "green", "blue" in 0..255, "intensity", ...), ``sensors`` (K×3: where the file
    says its sensors stood, a PCD's VIEWPOINT or a PTX file's scanners; with more than one,
    ``attributes["scan"]`` says whose each point is) and ``shift`` (subtracted from the file's
    coordinates, as for a georeferenced LAS file, so that float keeps their precision)."""

    def __init__(self, points, normals=None, attributes=None, sensors=None, shift=(0.0, 0.0, 0.0)):
        self.points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        self.normals = np.zeros((0, 3), np.float32) if normals is None else np.asarray(normals, np.float32)
        self.attributes = dict(attributes or {})
        self.sensors = np.zeros((0, 3)) if sensors is None else np.asarray(sensors, dtype=np.float64).reshape(-1, 3)
        self.shift = tuple(float(v) for v in shift)

    @property
    def colors(self):
        """N×3 uint8 colours, or None when the cloud has none."""
        return _colors(self.attributes, len(self.points))

    def __repr__(self):
        return f"Cloud({len(self.points)} points, attributes {sorted(self.attributes)})"


def _colors(attributes, count):
    channels = [attributes.get(name) for name in ("red", "green", "blue")]
    if any(c is None or len(c) != count for c in channels):
        return None
    return np.clip(np.rint(np.stack(channels, axis=1)), 0, 255).astype(np.uint8)


class Mesh:
    """A triangle mesh: ``vertices`` (N×3 float32), ``faces`` (M×3 int64, counter-clockwise seen
    from outside), ``normals`` (N×3, or 0×3 when the result has none), ``attributes`` (name ->
    one float32 per vertex, e.g. "degree" on PU meshes), ``statistics`` and ``job`` of the job
    that made it."""

    def __init__(self, vertices, faces, normals=None, attributes=None, job=None):
        self.vertices = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
        self.faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        self.normals = np.zeros((0, 3), np.float32) if normals is None else np.asarray(normals, np.float32)
        self.attributes = dict(attributes or {})
        self.job = job

    @property
    def statistics(self):
        return self.job.statistics if self.job is not None else {}

    @property
    def colors(self):
        """N×3 uint8 vertex colours (carried from a coloured cloud), or None when it has none."""
        return _colors(self.attributes, len(self.vertices))

    def __repr__(self):
        return f"Mesh({len(self.vertices)} vertices, {len(self.faces)} faces)"

    def welded_faces(self):
        """The faces with vertices at the same position made one, as STL export and most tools
        merge them."""
        v = self.vertices
        if len(v) == 0:
            return self.faces.copy()
        # Sorted by position, a vertex starts a new group when it differs from the one before.
        order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
        ordered = v[order]
        starts = np.ones(len(v), dtype=bool)
        starts[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
        group = np.empty(len(v), dtype=np.int64)
        group[order] = np.cumsum(starts) - 1
        return group[self.faces]

    def is_closed(self):
        """True when, with vertices merged by position, every edge borders exactly two faces that
        run along it in opposite directions (closed, manifold and consistently oriented)."""
        faces = self.welded_faces()
        if len(faces) == 0:
            return False
        start = faces.reshape(-1)
        end = faces[:, [1, 2, 0]].reshape(-1)
        if np.any(start == end):
            return False
        n = np.int64(faces.max() + 1)
        directed = np.sort(start * n + end)
        if np.any(directed[1:] == directed[:-1]):
            return False  # an edge run twice the same way: flipped or non-manifold
        # Each directed edge needs its reverse, and with no duplicates that makes every edge two faces.
        reverse = np.sort(end * n + start)
        return bool(np.array_equal(directed, reverse))

    def to_trimesh(self):
        """A ``trimesh.Trimesh`` (needs the trimesh package)."""
        import trimesh  # noqa: PLC0415 - optional

        colors = self.colors
        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces, process=False,
                               vertex_colors=colors if colors is not None else None)

    def to_open3d(self):
        """An ``open3d.geometry.TriangleMesh`` (needs the open3d package)."""
        import open3d  # noqa: PLC0415 - optional

        mesh = open3d.geometry.TriangleMesh(
            open3d.utility.Vector3dVector(self.vertices.astype(np.float64)),
            open3d.utility.Vector3iVector(self.faces.astype(np.int32)),
        )
        if len(self.normals) == len(self.vertices):
            mesh.vertex_normals = open3d.utility.Vector3dVector(self.normals.astype(np.float64))
        if self.colors is not None:
            mesh.vertex_colors = open3d.utility.Vector3dVector(self.colors.astype(np.float64) / 255.0)
        return mesh
