"""lsqsurf: surface and volume reconstruction on an lsqsurfd server, from NumPy arrays.

    import lsqsurf
    c = lsqsurf.Client("127.0.0.1:50051")
    mesh = c.reconstruct(points, method="iamls")   # points: N×3 array
    mesh.vertices, mesh.faces, mesh.statistics

See the README's Python section.
"""
from ._errors import JobFailed, RpcError
from ._types import Job, Mesh
from .client import CELL_TYPES, Client

__all__ = ["CELL_TYPES", "Client", "Job", "JobFailed", "Mesh", "RpcError"]
__version__ = "0.1.0"
