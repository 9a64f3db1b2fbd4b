"""lsqsurf: surface and volume reconstruction on an lsqsurfd server, from NumPy arrays.

    import lsqsurf
    c = lsqsurf.Client("127.0.0.1:50051")
    mesh = c.reconstruct(points, method="iamls")   # points: N×3 array
    mesh.vertices, mesh.faces, mesh.statistics
    scan = lsqsurf.read_cloud("scan.pcd")            # PLY, PCD, LAS, PTS, PTX, ...
    mesh = c.reconstruct(scan); mesh.colors          # its colours and sensors come along

See the README's Python section.
"""
from ._errors import JobFailed, RpcError
from ._types import Cloud, Job, Mesh
from .client import CELL_TYPES, Client, read_cloud

__all__ = ["CELL_TYPES", "Client", "Cloud", "Job", "JobFailed", "Mesh", "RpcError", "read_cloud"]
__version__ = "0.1.0"
