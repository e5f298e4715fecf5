import re

import numpy as np
import pytest
import torch

from meshmei.errors import MeshError
from meshmei.mesh import check_mesh, load_mesh, numpy_mesh, save_mesh
from meshmei.shapes import initial_mesh

from conftest import icosphere


def test_check_mesh_accepts_numpy_and_keeps_dtype():
    V, F = icosphere(1)
    V2, F2 = check_mesh(V.numpy().astype(np.float32), F.numpy().astype(np.int32))
    assert V2.dtype == torch.float32 and F2.dtype == torch.int64
    torch.testing.assert_close(V2.double(), V, rtol=1e-6, atol=1e-7)
    assert torch.equal(F2, F)


def test_check_mesh_does_not_copy_torch_vertices():
    V, F = icosphere(1)
    V2, _ = check_mesh(V, F)
    assert V2 is V


@pytest.mark.parametrize(
    "V, F, match",
    [
        (torch.zeros(4, 2), [[0, 1, 2]], r"V must have shape \(n, 3\), got \(4, 2\)"),
        (torch.zeros(4, 3, dtype=torch.int64), [[0, 1, 2]], "floating-point dtype, got torch.int64"),
        (torch.zeros(4, 3), torch.zeros(1, 3), "integer dtype, got torch.float32"),
        (torch.zeros(4, 3), [[0, 1, 2, 3]], "got faces with 4 corners"),
        (torch.zeros(4, 3), [0, 1, 2], r"F must have shape \(m, 3\), got \(3,\)"),
        (torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.int64), "V has no vertices"),
        (torch.zeros(4, 3), torch.zeros(0, 3, dtype=torch.int64), "F has no faces"),
        (torch.zeros(4, 3), [[0, 1, 4]], "vertex index 4, out of range for 4 vertices"),
        (torch.zeros(4, 3), [[0, -1, 2]], r"negative vertex index \(-1\)"),
        (torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, float("nan"), 0]]), [[0, 1, 2]], "NaN coordinates.*index 2"),
        (torch.tensor([[0.0, 0, 0], [1, 0, float("inf")], [0, 1, 0]]), [[0, 1, 2]], "Inf coordinates.*index 1"),
        ("not a mesh", [[0, 1, 2]], "V must be a torch tensor or numpy array, got str"),
        (torch.zeros(3, 3), [[0, 1], [0, 1, 2]], "ragged"),
        (torch.zeros(3, 3), torch.zeros(1, 3, dtype=torch.bool), "integer dtype, got torch.bool"),
    ],
)
def test_check_mesh_rejects(V, F, match):
    with pytest.raises(MeshError, match=match):
        check_mesh(V, F)


def test_check_mesh_batched():
    V, F = icosphere(1)
    Vb, _ = check_mesh(V.expand(2, -1, -1), F, batched=True)
    assert Vb.shape == (2, V.shape[0], 3)
    with pytest.raises(MeshError, match=r"\(B, n, 3\)"):
        check_mesh(V, F, batched=True)
    with pytest.raises(MeshError, match="batch is empty"):
        check_mesh(V.expand(0, -1, -1), F, batched=True)


def test_mesh_error_is_value_error():
    assert issubclass(MeshError, ValueError)


@pytest.mark.parametrize("ext", [".obj", ".ply", ".off", ".stl"])
def test_save_load_roundtrip(tmp_path, ext):
    V, F = icosphere(2)
    path = tmp_path / f"mesh{ext}"
    save_mesh(path, V, F)
    V2, F2 = load_mesh(path, dtype=torch.float64)
    if ext == ".stl":  # STL stores triangle soup: compare the face corner positions
        torch.testing.assert_close(V2[F2], V[F], rtol=0, atol=1e-6)
    else:
        # OBJ/OFF are text with trimesh's default precision; PLY stores float32
        torch.testing.assert_close(V2, V, rtol=0, atol=1e-6)
        assert torch.equal(F2, F)


def test_load_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        load_mesh(tmp_path / "missing.obj")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x00\x01 definitely not a mesh")
    with pytest.raises(MeshError, match="junk.ply"):
        load_mesh(junk)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(MeshError, match="empty"):
        load_mesh(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"nan\.obj: V holds NaN"):
        load_mesh(nan)


def test_a_mesh_too_small_for_float32_is_refused_and_float64_keeps_it(tmp_path):
    """A mesh 2e-300 across came back in float32 with every vertex at 0, without a word."""
    V, F = icosphere(1)
    tiny = tmp_path / "tiny.obj"
    save_mesh(tiny, V.double() * 1e-300, F)
    with pytest.raises(MeshError, match=r"tiny\.obj: the mesh is 2e-300 across, .* in torch.float32 its vertices "
                                        r"collapse .*use float64$"):
        load_mesh(tiny)
    V64 = load_mesh(tiny, dtype=torch.float64)[0]
    torch.testing.assert_close(V64 * 1e300, V.double(), rtol=1e-6, atol=0)


def test_paths_starting_with_a_tilde_are_the_home_folder(tmp_path, monkeypatch):
    """save_mesh made its partial file at the literal '~/...' path while trimesh wrote to the home folder: the
    rename failed and a stray partial file was left in the home folder."""
    monkeypatch.setenv("HOME", str(tmp_path))
    V, F = icosphere(0)
    save_mesh("~/sub/m.obj", V, F)
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["m.obj"]
    assert torch.equal(load_mesh("~/sub/m.obj")[1], F)


def test_save_mesh_rejects_unknown_format(tmp_path):
    V, F = icosphere(0)
    with pytest.raises(MeshError, match="unsupported mesh format '.xyz'"):
        save_mesh(tmp_path / "m.xyz", V, F)


def test_check_mesh_infers_the_batch_axis_with_batched_none():
    V, F = icosphere(1)
    Vb, _ = check_mesh(torch.stack([V, 2 * V]).numpy(), F, batched=None)
    assert Vb.shape == (2, V.shape[0], 3)
    assert check_mesh(V, F, batched=None)[0] is V
    with pytest.raises(MeshError, match=r"V must have shape \(n, 3\)"):
        check_mesh(torch.zeros(2, 4, 3), [[0, 1, 2]])


def test_numpy_mesh_gives_contiguous_float64_and_int64_arrays():
    V, F = icosphere(1)
    Vn, Fn = numpy_mesh(V.float(), F.int())
    assert Vn.dtype == np.float64 and Fn.dtype == np.int64
    assert Vn.flags.c_contiguous and Fn.flags.c_contiguous
    np.testing.assert_array_equal(Fn, F.numpy())
    with pytest.raises(MeshError, match="out of range"):
        numpy_mesh(V, F + V.shape[0])


def _write_uv_obj(path, V, F):
    """``(V, F)`` as an OBJ with per-corner texture coordinates wrapped around z: every face that crosses
    the seam gets texture coordinates of its own, so a reader splits the vertices there."""
    u = (np.arctan2(V[:, 1], V[:, 0]) / (2 * np.pi)) % 1.0
    lines = ["v %.17g %.17g %.17g" % tuple(p) for p in V.tolist()] + ["vt %.6f 0.5" % a for a in u]
    extra, faces = [], []
    for f in F.tolist():
        wraps = u[f].max() - u[f].min() > 0.5
        corners = []
        for c in f:
            if wraps and u[c] < 0.5:
                extra.append("vt %.6f 0.5" % (u[c] + 1))
                corners.append(f"{c + 1}/{len(V) + len(extra)}")
            else:
                corners.append(f"{c + 1}/{c + 1}")
        faces.append("f " + " ".join(corners))
    path.write_text("\n".join(lines + extra + faces) + "\n")


def test_load_mesh_welds_split_vertices_of_stl_and_uv_seams(tmp_path):
    from meshmei.quality import health_report

    V, F = icosphere(2)
    save_mesh(tmp_path / "plain.obj", V, F)
    save_mesh(tmp_path / "soup.stl", V, F)
    _write_uv_obj(tmp_path / "seam.obj", V.numpy(), F.numpy())
    plain = load_mesh(tmp_path / "plain.obj", dtype=torch.float64)
    plain_health = health_report(*plain)
    assert plain_health["watertight"] and plain_health["self_intersections"] == 0
    for name in ("soup.stl", "seam.obj"):
        V2, F2 = load_mesh(tmp_path / name, dtype=torch.float64)
        assert V2.shape == plain[0].shape and F2.shape == F.shape
        assert len(torch.unique(V2, dim=0)) == V2.shape[0]  # no two vertices left at one position
        # every face keeps its corners, in order (so its orientation), at the positions it had
        torch.testing.assert_close(V2[F2], V[F], rtol=0, atol=1e-6)
        assert health_report(V2, F2) == pytest.approx(plain_health)


def test_load_mesh_weld_drops_nothing_else(tmp_path):
    import trimesh

    # vertex 4 repeats vertex 0; vertex 3 is used by no face; face 2 has zero area once welded
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [9, 9, 9], [0, 0, 0], [0, 0, 1]])
    F = np.array([[0, 1, 2], [4, 2, 1], [0, 4, 1], [4, 1, 5]])
    path = tmp_path / "odd.ply"  # PLY keeps unused vertices (trimesh's OBJ reader drops them)
    trimesh.Trimesh(V, F, process=False, validate=False).export(str(path))
    V2, F2 = load_mesh(path, dtype=torch.float64)
    torch.testing.assert_close(V2, torch.from_numpy(V[[0, 1, 2, 3, 5]]))
    assert F2.tolist() == [[0, 1, 2], [0, 2, 1], [0, 0, 1], [0, 1, 4]]


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_load_mesh_names_a_point_cloud(tmp_path, suffix):
    import trimesh

    V, _ = icosphere(1)
    path = tmp_path / f"points{suffix}"
    trimesh.PointCloud(V.numpy()).export(str(path))
    with pytest.raises(MeshError, match=f"holds {V.shape[0]} points and no faces"):
        load_mesh(path)


def test_load_mesh_refuses_coordinates_beyond_the_dtype(tmp_path):
    path = tmp_path / "far.obj"
    path.write_text("v 0 0 0\nv 1e39 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"far\.obj: coordinates up to 1e\+39 do not fit in torch\.float32"):
        load_mesh(path)
    V, _ = load_mesh(path, dtype=torch.float64)
    assert bool(torch.isfinite(V).all()) and float(V.max()) == 1e39


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32, np.uint64])
def test_check_mesh_accepts_unsigned_faces(dtype):
    V, F = icosphere(1)
    for faces in (F.numpy().astype(dtype), torch.from_numpy(F.numpy().astype(dtype))):
        V2, F2 = check_mesh(V, faces)
        assert F2.dtype == torch.int64 and torch.equal(F2, F)
    with pytest.raises(MeshError, match=f"vertex index {V.shape[0]}, out of range"):
        check_mesh(V, (F.numpy() + 1).astype(dtype))


def test_check_mesh_refuses_uint64_faces_beyond_int64():
    F = np.array([[0, 1, 2 ** 63 + 5]], dtype=np.uint64)
    with pytest.raises(MeshError, match=f"vertex index {2 ** 63 + 5} \\(torch.uint64\\), too large"):
        check_mesh(torch.zeros(3, 3), F)


def test_the_same_int32_or_numpy_face_array_is_converted_once():
    """check_mesh handed back a new int64 tensor on every call for int32 or numpy faces, so the topology
    cache keyed by that tensor never hit (rebuilt every call, about 17x slower at 20,000 faces)."""
    V, F = initial_mesh("sphere", n_vertices=200)
    for Fx in (F.int(), F.numpy().copy()):
        F1, F2 = check_mesh(V, Fx)[1], check_mesh(V, Fx)[1]
        assert F1 is F2 and F1.dtype == torch.int64 and torch.equal(F1, F)
        Fx[0] = Fx[0, [0, 2, 1]]  # edited: checked and converted anew
        F3 = check_mesh(V, Fx)[1]
        assert F3 is not F1 and torch.equal(F3[0], F[0, [0, 2, 1]])


def test_numpy_faces_with_negative_strides_are_taken():
    """F[:, ::-1] (faces turned over) gave torch's 'negative stride' ValueError."""
    V, F = initial_mesh("sphere", n_vertices=200)
    Fn = F.numpy()
    _, Fr = check_mesh(V.numpy()[:, ::-1], Fn[:, ::-1])
    assert torch.equal(Fr, F.flip(1))


def test_faces_handed_out_and_edited_in_place_are_checked_again():
    """check_mesh hands back one int64 tensor per unchanged int32 or numpy source (for the topology cache);
    an in-place edit of that tensor was handed back, unchecked, by the next call (index 999 on 4 vertices)."""
    import numpy as np

    V = torch.rand(4, 3)
    F32 = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    _, G = check_mesh(V, F32)
    assert check_mesh(V, F32)[1] is G  # the cache hits while nothing changed
    G[0, 0] = 999
    _, again = check_mesh(V, F32)
    assert again is not G and again.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_an_obj_of_two_dimensional_vertices_is_a_mesh_error(tmp_path):
    p = tmp_path / "flat.obj"
    p.write_text("v 0 0\nv 1 0\nv 0 1\nv 1 1\nf 1 2 3\nf 2 4 3\n")  # a plain ValueError from a reshape before
    with pytest.raises(MeshError, match=r"flat.obj: vertices must have 3 coordinates, got an array of shape \(4, 2\)$"):
        load_mesh(p)


def test_an_interrupted_save_leaves_the_old_file_whole_and_no_partial_one(tmp_path, monkeypatch):
    """save_mesh wrote in place: a cut OBJ loaded as a smaller mesh without a word."""
    import trimesh

    V, F = initial_mesh("sphere", n_vertices=100)
    path = tmp_path / "m.obj"
    save_mesh(path, V, F)
    before = path.read_bytes()

    def cut(self, file_obj=None, **kw):  # writes half of the file, then the process is interrupted
        data = trimesh.exchange.export.export_mesh(self, None, file_type="obj")
        with open(file_obj, "w") as fh:
            fh.write(data[: len(data) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(trimesh.Trimesh, "export", cut)
    with pytest.raises(KeyboardInterrupt):
        save_mesh(path, V * 2.0, F)
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["m.obj"]


def test_a_mesh_touching_itself_at_a_point_reads_back_as_written(tmp_path):
    """Welding equal positions made the teapot's handle tip, which touches its body, one bow-tie vertex: a saved
    teapot read back with 8257 vertices, Euler characteristic 1 and 276 intersecting pairs for 294. Each fan
    now keeps its own vertex, so PLY gives back the mesh exactly, and an STL soup welds into the same
    topology."""
    from meshmei.quality import count_self_intersections, topology
    from meshmei.shapes import target_mesh

    V, F = target_mesh("teapot")
    for suffix in (".ply", ".stl"):
        save_mesh(tmp_path / f"teapot{suffix}", V, F)
        V2, F2 = load_mesh(tmp_path / f"teapot{suffix}", dtype=V.dtype)
        assert topology(F2) == topology(F) and topology(F2)["nonmanifold_vertices"] == 0
        assert count_self_intersections(V2.double(), F2) == count_self_intersections(V.double(), F)
        if suffix == ".ply":
            assert torch.equal(F2, F) and torch.equal(V2, V)
    # two tetrahedra touching at a corner, as a soup: each closes on its own, the corner is not shared
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    V = np.concatenate([tet, -tet])
    F = np.concatenate([tf, tf[:, ::-1] + 4])
    save_mesh(tmp_path / "touch.stl", V, F)
    V2, F2 = load_mesh(tmp_path / "touch.stl", dtype=torch.float64)
    assert V2.shape == (8, 3) and topology(F2)["nonmanifold_vertices"] == 0
    torch.testing.assert_close(V2[F2], torch.from_numpy(V[F]))


@pytest.mark.parametrize("suffix", [".obj", ".off"])
def test_a_tiny_mesh_keeps_its_shape_in_text_formats(tmp_path, suffix):
    """OBJ and OFF are written at a fixed count of decimals: a mesh 1e-9 across was written as one point and
    read back as one vertex with every face [0, 0, 0], without a word. The decimals now grow as the mesh
    shrinks, so its relative precision is that of a unit mesh."""
    V, F = icosphere(2)
    V = V.double() * 1e-9
    save_mesh(tmp_path / f"tiny{suffix}", V, F)
    V2, F2 = load_mesh(tmp_path / f"tiny{suffix}", dtype=torch.float64)
    assert torch.equal(F2, F)
    assert float((V2 - V).abs().max()) <= 1e-8 * 1e-9


@pytest.mark.parametrize("face", ["f 0 1 2", "f 2 3 0", "f\t0 1 2", "f 1/0/1 2/0/2 3//3", "f 1//1 2//2 3//0", "f 2 3 0\r"])
def test_an_obj_with_index_0_is_refused_naming_its_line(tmp_path, face):
    """OBJ counts from 1; trimesh read index 0 as the last vertex, so a 0-based file came back as another,
    degenerate mesh without a word (and a texture index 0 turned the face into one point)."""
    path = tmp_path / "zero.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 1\n" + face + "\n")
    with pytest.raises(MeshError, match=r"zero.obj, line 9: a face uses index 0; OBJ indices count from 1"):
        load_mesh(path)


def test_obj_indices_that_only_contain_0_still_load(tmp_path):
    path = tmp_path / "ten.obj"
    path.write_text("".join(f"v {i} {i % 3} {i % 5}\n" for i in range(12)) + "vt 0 0\n" * 12
                    + "f 10/10 2/1 3/2\nf 1 11 12\nf -1 -2 -3\n")
    V, F = load_mesh(path, dtype=torch.float64)  # the reader renumbers the vertices: compare corners
    corner = [[[float(i), i % 3, i % 5] for i in face] for face in ([9, 1, 2], [0, 10, 11], [11, 10, 9])]
    assert V[F].tolist() == corner


def test_load_mesh_takes_float_dtypes_and_their_names_only(tmp_path):
    path = tmp_path / "tri.obj"
    save_mesh(path, torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), torch.tensor([[0, 1, 2]]))
    assert load_mesh(path, dtype="float64")[0].dtype == torch.float64
    for dtype in (torch.int64, torch.complex64, "int64", "cuda", np.float32):
        with pytest.raises(MeshError, match="dtype must be a torch floating dtype"):
            load_mesh(path, dtype=dtype)


@pytest.mark.parametrize("suffix", [".ply", ".stl"])
def test_save_mesh_refuses_coordinates_the_formats_float32_cannot_hold(tmp_path, suffix):
    """PLY and STL store float32: a mesh 1e-50 across was written as one point and read back as the face
    [0, 0, 0]; one at 1e300 was written as inf. OBJ keeps every digit."""
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    F = torch.tensor([[0, 1, 2]])
    for scale, says in ((1e-50, "its vertices collapse"), (1e300, "do not fit in torch.float32")):
        with pytest.raises(MeshError, match=rf"{suffix[1:].upper()} stores float32.*{says}"):
            save_mesh(tmp_path / f"m{suffix}", V * scale, F)
        assert not list(tmp_path.iterdir())
    save_mesh(tmp_path / "m.obj", V * 1e-50, F)
    assert torch.equal(load_mesh(tmp_path / "m.obj", dtype=torch.float64)[0], V * 1e-50)


@pytest.mark.parametrize("where", ["V", "F", "both"])
def test_a_meta_tensor_is_a_mesh_error_naming_it(where):
    """Found by fuzzing: a mesh on torch's "meta" device (shapes, no values) ended in torch's 'Tensor.item()
    cannot be called on meta tensors' from the face checks, or aten::equal's NotImplementedError."""
    from meshmei.mesh import as_faces, check_rest_pose

    V, F = icosphere(1)
    Vm = V.to("meta") if where != "F" else V
    Fm = F.to("meta") if where != "V" else F
    name, shape, dtype = ("F", tuple(F.shape), "int64") if where == "F" else ("V", tuple(V.shape), "float64")
    with pytest.raises(MeshError, match=rf"^{name} is a meta tensor \(shape {re.escape(str(shape))}, torch\.{dtype}\): "
                                        "torch's 'meta' device holds no values; give the mesh on the CPU or a GPU$"):
        check_mesh(Vm, Fm)
    if where == "F":
        with pytest.raises(MeshError, match=r"^F is a meta tensor"):
            as_faces(Fm)
    if where == "V":
        with pytest.raises(MeshError, match=r"^V0 is a meta tensor"):
            check_rest_pose(Vm, V, F)
