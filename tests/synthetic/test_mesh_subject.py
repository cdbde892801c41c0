"""A user's own subject from blendshape meshes."""
import json

import numpy as np
import pytest
import trimesh

from mifacerf.synthetic import SubjectScene, load_mesh_subject
from mifacerf.synthetic.mesh_subject import MeshSubjectError


def _face(sub=3):
    """A head-sized ellipsoid cap facing +Z with an open 'mouth' slot."""
    m = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
    V = m.vertices * np.array([0.075, 0.11, 0.09])
    keep = V[:, 2] > -0.02
    F = m.faces[keep[m.faces].all(1)]
    c = V[F].mean(1)
    F = F[~((np.abs(c[:, 0]) < 0.02) & (np.abs(c[:, 1] + 0.05) < 0.004) & (c[:, 2] > 0))]   # the mouth
    used = np.unique(F)
    remap = -np.ones(len(V), int)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def _write(path, V, F):
    trimesh.Trimesh(V, F, process=False).export(path)


@pytest.fixture
def folder(tmp_path):
    V, F = _face()
    _write(tmp_path / "neutral.obj", V, F)
    jaw = V.copy()
    low = jaw[:, 1] < -0.05
    jaw[low, 1] -= 0.01 * (1 + (-0.05 - jaw[low, 1]) / 0.06)
    _write(tmp_path / "jawOpen.obj", jaw, F)
    smile = V.copy()
    smile[:, 0] *= 1 + 0.08 * np.exp(-((V[:, 1] + 0.05) / 0.02) ** 2)
    _write(tmp_path / "mouthSmile.obj", smile, F)
    return tmp_path


def test_mesh_subject_interface(folder, mi):
    s = load_mesh_subject(folder, texture_resolution=512)
    assert [c.name for c in s.controls] == ["jawOpen", "mouthSmile"]
    assert all(c.lo == 0 and c.hi == 1 and c.default == 0 for c in s.controls)
    p = s.params(jawOpen=1.0)
    pose = s.pose(p)
    V0 = trimesh.load(folder / "neutral.obj", process=False, maintain_order=True).vertices
    V1 = trimesh.load(folder / "jawOpen.obj", process=False, maintain_order=True).vertices
    o = s.offset                                      # placement "auto": nose tip on the embedded head's
    np.testing.assert_allclose(o + V0[np.argmax(V0[:, 2])], [0.0, -0.0267, 0.1127], atol=1e-9)
    np.testing.assert_allclose(pose.skin_vertices, V1 + o, atol=1e-6)
    half = s.pose(s.params(jawOpen=0.5, mouthSmile=0.5)).skin_vertices
    V2 = trimesh.load(folder / "mouthSmile.obj", process=False, maintain_order=True).vertices
    np.testing.assert_allclose(half, V0 + o + 0.5 * (V1 - V0) + 0.5 * (V2 - V0), atol=1e-6)
    np.testing.assert_allclose(s.neutral.skin_vertices, V0 + o, atol=1e-6)
    # dots: evenly sampled, painted, exact in every pose
    assert len(s.dot_tri) == 300
    d = np.linalg.norm(s.dots_neutral[:, None] - s.dots_neutral[None], axis=-1)
    np.fill_diagonal(d, 1)
    assert d.min() > 0.002
    want = np.einsum("nk,nkj->nj", s.dot_bary, pose.skin_vertices[s.skin_faces[s.dot_tri]])
    np.testing.assert_allclose(pose.dots, want)
    assert pose.textures.albedo.shape == (512, 512, 3)
    assert (np.abs(pose.textures.albedo - [0.9, 0.85, 0.1]).max(-1) < 0.05).sum() > 50   # yellow dots
    # template: the dots, a mesh without the slot, coarse points, regions, extensions beyond the dots
    t = s.template
    assert t.kinds.count("dot") == 300 and len(t.coarse_points) == 18 and t.teeth == {} and t.eyes == {}
    assert len(t.triangles) > 400
    # (this slot is pinched: its boundary touches itself, so it is no margin loop and the template may
    # bridge it; the head of test_mesh_subject_loader.py has real openings, kept open with their margins)
    assert sum(len(v) for v in t.regions.values()) == t.n_vertices
    assert s.template_info["coverage"] >= 0.98
    u = type(t).from_json(t.to_json())
    np.testing.assert_array_equal(u.triangles, t.triangles)
    # presets of the usual sizes
    for n in (6, 24, 60):
        ex = s.presets(n)
        assert ex[0].name == "neutral" and len({e.name for e in ex}) == len(ex) <= n
    assert pose.parts == {}
    # renders in a SubjectScene
    sc = SubjectScene(s)
    sc.set_pose(pose)
    ray = mi.Ray3f(mi.Point3f(*[float(c) for c in o + [0.0, 0.0, 0.5]]), mi.Vector3f(0.0, 0.0, -1.0))
    pid, face = sc.classify(sc.scene.ray_intersect(ray))
    assert int(pid[0]) == 1 and bool(face[0])


def test_explicit_files_manifest_and_albedo(folder, tmp_path):
    import imageio.v3 as iio

    img = np.zeros((64, 64, 3), np.uint8)
    img[..., 0] = 200
    iio.imwrite(folder / "albedo.png", img)
    # these meshes have no texture coordinates: the albedo cannot be mapped, and saying so is the answer
    with pytest.raises(MeshSubjectError, match="no texture coordinates"):
        load_mesh_subject(folder / "neutral.obj", {"open": folder / "jawOpen.obj"}, albedo=folder / "albedo.png",
                          texture_resolution=512, n_dots=50)
    (folder / "albedo.png").unlink()
    s = load_mesh_subject(folder / "neutral.obj", {"open": folder / "jawOpen.obj"}, texture_resolution=512, n_dots=50)
    assert [c.name for c in s.controls] == ["open"]
    (folder / "subject.json").write_text(json.dumps({
        "neutral": "neutral.obj", "expressions": {"jaw": "jawOpen.obj"},
        "presets": [{"name": "half_open", "category": "viseme", "weights": {"jaw": 0.5}}]}))
    s = load_mesh_subject(folder, texture_resolution=512, n_dots=40)
    names = [e.name for e in s.presets(6)]
    assert names[:2] == ["neutral", "half_open"]


def test_bad_inputs_have_clear_errors(folder, tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("bad")
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        load_mesh_subject(folder / "neutral.obj", {"x": folder / "nope.obj"})
    with pytest.raises(FileNotFoundError, match="neutral"):
        load_mesh_subject(tmp_path / "missing_neutral.obj", {"x": folder / "jawOpen.obj"})
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="neutral"):
        load_mesh_subject(empty)
    V, F = _face(sub=2)                                   # other topology
    _write(tmp_path / "other.obj", V, F)
    with pytest.raises(MeshSubjectError, match="topology"):
        load_mesh_subject(folder / "neutral.obj", {"other": tmp_path / "other.obj"})
    V0 = trimesh.load(folder / "neutral.obj", process=False, maintain_order=True)
    (tmp_path / "nan.obj").write_text(
        "\n".join([f"v {x} {y} {z}" for x, y, z in V0.vertices[:-1]] + ["v nan 0 0"]
                  + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in V0.faces]))
    with pytest.raises(MeshSubjectError, match="NaN"):
        load_mesh_subject(folder / "neutral.obj", {"bad": tmp_path / "nan.obj"})
    with pytest.raises(MeshSubjectError, match="metres"):
        load_mesh_subject(folder / "neutral.obj", {"j": folder / "jawOpen.obj"}, scale=100.0)
    with pytest.raises(MeshSubjectError, match="at least one"):
        load_mesh_subject(folder / "neutral.obj", {})
    s = load_mesh_subject(folder, texture_resolution=512, n_dots=20)
    with pytest.raises(KeyError):
        s.params(nope=1)
    with pytest.raises(ValueError):
        s.pose(np.array([np.nan, 0.0]))
