"""Mesh.is_closed against shapes whose answer is known, with vertices repeated per face as STL
files and some exporters write them."""
import numpy as np

from lsqsurf import Mesh

CORNERS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
# Counter-clockwise seen from outside.
FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def split(faces):
    """Every face with vertices of its own (the same positions repeated)."""
    return Mesh(CORNERS[faces.reshape(-1)], np.arange(faces.size).reshape(-1, 3))


def test_a_tetrahedron_is_closed_shared_or_split():
    assert Mesh(CORNERS, FACES).is_closed()
    assert split(FACES).is_closed()
    assert len(np.unique(split(FACES).welded_faces())) == 4


def test_a_missing_or_flipped_face_is_not_closed():
    assert not split(FACES[1:]).is_closed()
    flipped = FACES.copy()
    flipped[0] = flipped[0, [0, 2, 1]]
    assert not split(flipped).is_closed()
    assert not Mesh(CORNERS, np.zeros((0, 3), int)).is_closed()


def test_two_tetrahedra_sharing_an_edge_are_not_manifold():
    moved = CORNERS.copy()
    moved[2:] = [[0, -1, 0], [0, 0, -1]]  # shares the edge 0-1 with the first
    both = Mesh(np.concatenate([CORNERS, moved]), np.concatenate([FACES, FACES + 4]))
    assert Mesh(moved, FACES[:, [0, 2, 1]]).is_closed()
    faces = np.concatenate([FACES, FACES[:, [0, 2, 1]] + 4])
    assert not Mesh(np.concatenate([CORNERS, moved]), faces).is_closed()
    assert both.welded_faces().max() == 5
