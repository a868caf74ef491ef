"""Mesh reading (OFF, COFF with colours, polygons fanned, OBJ) and the shared data set."""
from pathlib import Path

import numpy as np
import pytest

from cljn_addon.core import InputError
from cljn_addon.core.evaluation.shapes import signed_volume
from cljn_addon.core.formats.meshes import find_meshes, read_mesh

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"


def test_off_with_colours_and_a_quad(tmp_path):
    path = tmp_path / "quad.off"
    path.write_text("COFF\n# a comment\n4 1 0\n0 0 0 255 0 0 255\n1 0 0 255 0 0 255\n"
                    "1 1 0 0 255 0 255\n0 1 0 0 0 255 255\n4 0 1 2 3\n")
    v, f = read_mesh(path)
    assert v.shape == (4, 3) and np.array_equal(v[2], [1, 1, 0])
    assert f.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_off_counts_on_the_header_line(tmp_path):
    path = tmp_path / "tri.off"
    path.write_text("OFF 3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert read_mesh(path)[1].tolist() == [[0, 1, 2]]


def test_obj_with_slashes_and_negative_indices(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\nf -4 -2 -1\n")
    v, f = read_mesh(path)
    assert f.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 3]]


@pytest.mark.parametrize("text, message", [
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n", "truncated"),
    ("OFF\n3 1 0\n0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n", "line 4"),
    ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "does not exist"),
    ("PLY\n", "OFF header"),
])
def test_bad_off_files_name_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.off"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_mesh(path)


def test_unsupported_and_missing(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_mesh(tmp_path / "none.off")
    (tmp_path / "a.stl").write_text("solid")
    with pytest.raises(InputError, match="unsupported"):
        read_mesh(tmp_path / "a.stl")


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data/meshes is not present")
def test_shared_meshes_read_and_are_closed_solids():
    paths = find_meshes(SHARED / "validation") + find_meshes(SHARED / "train")[:5]
    assert len(paths) >= 5
    for path in paths:
        v, f = read_mesh(path)
        assert len(f) > 0 and np.isfinite(v).all(), path
        assert abs(signed_volume(v, f)) > 0, path


def test_ply_mesh_with_a_quad(tmp_path):
    path = tmp_path / "quad.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    v, f = read_mesh(path)
    assert np.array_equal(v[2], [1, 1, 0])
    assert f.tolist() == [[0, 1, 2], [0, 2, 3]]
