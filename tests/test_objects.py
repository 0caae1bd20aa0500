import numpy as np
import pytest

from completion import objects as O


def test_every_family_builds_in_size_range():
    for family in O.FAMILIES:
        for k in (0, 9):
            m = O.load_object(f"proc/{family}/{k}")
            size = m.extents.max()
            assert O.SIZE_RANGE_M[0] - 1e-9 <= size <= O.SIZE_RANGE_M[1] + 1e-9
            np.testing.assert_allclose(m.bounds.mean(0), 0, atol=1e-9)
    assert len(O.FAMILIES) >= 8


def test_ids_are_stable_and_splits_disjoint():
    a = O.load_object("proc/mug/17")
    b = O.load_object("proc/mug/17")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    train, val, test = (set(O.object_ids(s)) for s in O.SPLITS)
    assert not (train & val) and not (train & test) and not (val & test)
    assert O.split_of("urdf/799") == "train" and O.split_of("urdf/850") == "val"
    assert O.split_of("urdf/900") == "test" and O.split_of("named/duck") == "test"
    assert set(O.object_ids("test", sources=("named",))) == {f"named/{n}" for n in O.NAMED_OBJECTS}


def test_named_objects_load():
    for name in O.NAMED_OBJECTS:
        m = O.load_object(f"named/{name}")
        assert len(m.faces) > 0 and 0.08 - 1e-9 <= m.extents.max() <= 0.2 + 1e-9


def test_user_folder(tmp_path):
    import trimesh

    trimesh.creation.box(extents=[0.1, 0.05, 0.02]).export(tmp_path / "a.stl")
    trimesh.creation.icosphere().export(tmp_path / "b.ply")  # radius 1 m: rescaled to 15 cm
    (tmp_path / "notes.txt").write_text("ignored")
    ids = O.objects_in_folder(tmp_path)
    assert [i.rsplit("/", 1)[1] for i in ids] == ["a.stl", "b.ply"]
    assert O.load_object(ids[0]).extents.max() == pytest.approx(0.1)
    assert O.load_object(ids[1]).extents.max() == pytest.approx(0.15)
    with pytest.raises(ValueError, match="no OBJ/STL/PLY"):
        O.objects_in_folder(tmp_path / "..") if False else O.objects_in_folder(_empty(tmp_path))


def _empty(tmp_path):
    d = tmp_path / "empty"
    d.mkdir()
    return d


def test_bad_ids_are_explained():
    with pytest.raises(ValueError, match="unknown object id"):
        O.load_object("nonsense")
    with pytest.raises(ValueError, match="not found"):
        O.load_object("file:/does/not/exist.obj")


@pytest.mark.slow
def test_every_object_of_every_split_loads_except_the_listed_unreadable_ones():
    failed = set()
    for split in O.SPLITS:
        for object_id in O.object_ids(split, sources=("proc", "urdf", "named")):
            try:
                mesh = O.load_object(object_id)
            except ValueError:
                failed.add(object_id)
                continue
            assert len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all(), object_id
    assert failed == O.UNREADABLE
