"""save_face_model / load_face_model: the face model file that ``torchface track --model`` reads; its round trip is
exact, its content digest, and what it refuses (a missing, foreign, later or damaged file, a model that fails
load_mesh_model's checks)."""

from __future__ import annotations

import io
import zipfile
from dataclasses import fields, replace

import numpy as np
import pytest
import torch
import trimesh

from torchface.io.errors import InputError
from torchface.model import (
    AnimationSet,
    face_model_digest,
    load_candide3,
    load_face_model,
    load_mesh_model,
    save_face_model,
)
from torchface.model.model_file import FORMAT_VERSION


def _same(a, b) -> bool:
    """Every field of two FaceModels equal, tensors to the bit and in the same dtype."""
    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, torch.Tensor):
            if x.dtype != y.dtype or x.shape != y.shape or not torch.equal(x, y):
                return False
        elif x != y:
            return False
    return True


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_round_trip_is_exact_in_the_models_dtype(tmp_path, dtype):
    model = load_candide3(AnimationSet.AUV_AND_FAP, dtype=dtype)
    path = tmp_path / "candide"  # (no suffix: written as named, not candide.npz)
    save_face_model(model, path)
    assert path.is_file() and not (tmp_path / "candide.npz").exists()
    assert _same(load_face_model(path, dtype=dtype), model)


def test_a_float64_file_loads_as_the_loaders_float32(tmp_path):
    """A model saved in float64 is rounded once on loading, as load_candide3 rounds its float64 arithmetic."""
    save_face_model(load_candide3(dtype=torch.float64), tmp_path / "c.npz")
    assert _same(load_face_model(tmp_path / "c.npz"), load_candide3())


def test_a_mesh_model_round_trips_with_its_own_names(tmp_path):
    c = load_candide3(dtype=torch.float64)
    mesh = trimesh.Trimesh(c.mean.numpy(), c.faces.numpy(), process=False)
    model = load_mesh_model(mesh, blendshapes=c.animation_units[:2], blendshape_names=["a", "b"],
                            facs_links={"a": ("AU1", "AU2")}, landmark_vertices=c.landmark_vertices[:, 0],
                            name="mine")  # fmt: skip
    save_face_model(model, tmp_path / "m.npz")
    back = load_face_model(tmp_path / "m.npz")
    assert _same(back, model) and back.name == "mine" and back.num_shape == 0


def test_digest_follows_the_content_not_the_dtype_label():
    a = load_candide3()
    assert face_model_digest(a) == face_model_digest(load_candide3())
    assert face_model_digest(a) != face_model_digest(load_candide3(dtype=torch.float64))  # other values
    assert face_model_digest(a) != face_model_digest(replace(a, name="other"))
    assert face_model_digest(a) != face_model_digest(load_candide3(AnimationSet.AUV_AND_FAP))


def _archive(path, **changes) -> None:
    """Rewrite the face model file ``path`` with entries changed (None: removed)."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update({k: v for k, v in changes.items() if v is not None})
    for k in [k for k, v in changes.items() if v is None]:
        del arrays[k]
    with open(path, "wb") as out:
        np.savez(out, **arrays)


def test_bad_files_are_refused_with_one_line(tmp_path):
    good = tmp_path / "good.npz"
    save_face_model(load_candide3(), good)
    cases = {"missing": (tmp_path / "nope.npz", "no such face model file"), "folder": (tmp_path, "a folder")}
    text = tmp_path / "text.npz"
    text.write_text("hello\n")
    cases["text"] = (text, "not a torchface face model file .*: not an .npz archive")
    npy = tmp_path / "one.npy"
    np.save(npy, np.zeros(3))
    cases["npy"] = (npy, "one .npy array")
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    cases["empty"] = (empty, "not an .npz archive")
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[:2000])
    cases["truncated"] = (cut, "not a torchface face model file")
    other = tmp_path / "other.npz"
    np.savez(other, mean=np.zeros((3, 3)))
    cases["foreign"] = (other, "its format entry is missing")
    for name, change, said in (
        ("later", {"format_version": np.array(FORMAT_VERSION + 1)}, "written by a later torchface"),
        ("lacks", {"faces": None}, "it lacks faces"),
        ("kind", {"faces": np.zeros((2, 3))}, "faces holds float64, not integer values"),
        ("shape", {"landmark_weights": np.ones((68, 2), np.float32)}, "landmark_weights must have shape"),
        ("nan", {"mean": np.full((113, 3), np.nan, np.float32)}, "mean holds non-finite values"),
        ("mask", {"surface_vertex_mask": np.zeros(113, bool)}, "surface_vertex_mask must be True for exactly"),
    ):
        p = tmp_path / f"{name}.npz"
        p.write_bytes(good.read_bytes())
        _archive(p, **change)
        cases[name] = (p, said)
    for name, (path, said) in cases.items():
        with pytest.raises(InputError, match=said) as info:
            load_face_model(path)
        assert "\n" not in str(info.value), name
    with zipfile.ZipFile(cut.with_name("pickled.npz"), "w") as z:  # an object array: never unpickled
        buf = io.BytesIO()
        np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        z.writestr("format.npy", buf.getvalue())
    with pytest.raises(InputError, match="not a torchface face model file"):
        load_face_model(cut.with_name("pickled.npz"))


def test_entries_of_other_names_are_left_unread(tmp_path):
    """An entry this version does not know (a later version's, which keeps the format version: the module's
    docstring) is left unread, whatever it holds: an object array in one refused the file ("Object arrays cannot be
    loaded when allow_pickle=False"), as every entry was read."""
    c = load_candide3()
    p = tmp_path / "c.npz"
    save_face_model(c, p)
    with zipfile.ZipFile(p, "a") as z:
        buf = io.BytesIO()
        np.save(buf, np.array([{"uv": 1}], dtype=object), allow_pickle=True)
        z.writestr("texture_coordinates.npy", buf.getvalue())
    assert _same(load_face_model(p), c)


def test_the_checks_of_load_mesh_model_are_made(tmp_path):
    """A model wound inward is refused as load_mesh_model refuses it; a blendshape that is a whole mesh too; 68
    landmarks mirrored warn as there. (The files are made by rewriting a good one's entries: save_face_model now
    refuses to write such models, test_save_refuses_a_model_that_load_would_refuse; they were saved with it.)"""
    c = load_candide3()
    p = tmp_path / "m.npz"
    save_face_model(c, p)
    _archive(p, faces=c.faces.flip(1).numpy())
    with pytest.raises(InputError, match="faces away from the viewer"):
        load_face_model(p)
    whole = c.animation_units.clone()
    whole[0] = c.mean
    save_face_model(c, p)
    _archive(p, animation_units=whole.numpy())
    with pytest.raises(InputError, match="is a whole mesh, not a displacement"):
        load_face_model(p)
    with pytest.warns(UserWarning, match="not laid out as the iBUG-68 points"):  # (saving warns as loading does)
        save_face_model(replace(c, mean=c.mean * torch.tensor([-1.0, 1.0, 1.0]), faces=c.faces.flip(1)), p)
    with pytest.warns(UserWarning, match="not laid out as the iBUG-68 points"):
        load_face_model(p)


def test_save_refuses_a_model_that_load_would_refuse(tmp_path):
    """A model wound inward, or with a blendshape that is a whole mesh, is refused by save_face_model with
    load_face_model's reason, and nothing is written (it was written, and refused only by ``torchface track
    --model``); one whose landmarks are mirrored warns when saved, as when loaded, and is written."""
    c = load_candide3()
    p = tmp_path / "m.npz"
    with pytest.raises(ValueError, match=r"'CANDIDE-3 v3.1.6' is not saved: load_face_model would refuse it: .*faces "
                                         "away from the viewer"):  # fmt: skip
        save_face_model(replace(c, faces=c.faces.flip(1)), p)
    whole = c.animation_units.clone()
    whole[2] = c.mean
    with pytest.raises(ValueError, match=r"animation_units\[2\] .* is a whole mesh, not a displacement"):
        save_face_model(replace(c, animation_units=whole), p)
    assert not list(tmp_path.iterdir())
    save_face_model(c, p)  # an earlier file is kept
    before = p.read_bytes()
    with pytest.raises(ValueError, match="faces away from the viewer"):
        save_face_model(replace(c, faces=c.faces.flip(1)), p)
    assert p.read_bytes() == before and [q.name for q in tmp_path.iterdir()] == ["m.npz"]
    with pytest.warns(UserWarning, match="not laid out as the iBUG-68 points") as caught:
        save_face_model(replace(c, mean=c.mean * torch.tensor([-1.0, 1.0, 1.0]), faces=c.faces.flip(1)), p)
    assert caught[0].filename == __file__  # (the warning names the caller)
    with pytest.warns(UserWarning, match=r"are the blendshapes in the mesh's unit"):  # (its blendshapes not scaled)
        with pytest.warns(UserWarning, match=r"the mesh spans 0.\d+ mm in the model; .* is the model in millimetres"):
            save_face_model(replace(c, mean=c.mean / 1000), p)


def test_save_refuses_what_it_cannot_keep(tmp_path):
    with pytest.raises(TypeError, match="must be a FaceModel"):
        save_face_model("candide", tmp_path / "x.npz")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="NUL"):
        save_face_model(replace(load_candide3(), name="a\0"), tmp_path / "x.npz")
    c = load_candide3()  # (the message names the name: it said "a name ends in a NUL character")
    with pytest.raises(ValueError, match=r"animation_names: 'AUV3 Brow lowerer\\x00' ends in a NUL"):
        save_face_model(replace(c, animation_names=tuple(n + "\0" if k == 3 else n for k, n in enumerate(c.animation_names))), tmp_path / "x.npz")
    assert not list(tmp_path.iterdir())
    with pytest.raises(TypeError, match="floating"):
        load_face_model(tmp_path / "x.npz", dtype=torch.int64)


def test_device_is_checked_before_the_file_is_read(tmp_path):
    """A device this machine lacks is load_candide3's one ValueError naming it (it was torch's RuntimeError "Invalid
    device string", an AssertionError "Torch not compiled with CUDA enabled" or, for "meta", a RuntimeError from the
    model's checks), before the file is read, as load_mesh_model checks it."""
    save_face_model(load_candide3(), tmp_path / "c.npz")
    for path in (tmp_path / "c.npz", tmp_path / "nope.npz"):
        for device in ("gpu0", "meta"):
            with pytest.raises(ValueError, match=f"'{device}'.*devices here: cpu"):
                load_face_model(path, device=device)


def test_a_file_of_the_other_byte_order_loads_as_its_own(tmp_path):
    """Arrays of the other byte order (np.savez keeps the writing machine's: a big-endian one's file) load as the
    same model (torch refused them: a bare ValueError "given numpy array has byte order different ...")."""
    model = load_candide3()
    p = tmp_path / "c.npz"
    save_face_model(model, p)
    with np.load(p, allow_pickle=False) as data:
        swapped = {k: data[k].astype(data[k].dtype.newbyteorder("S")) for k in data.files}
    assert swapped["mean"].dtype.byteorder != "=" and swapped["name"].dtype.byteorder != "="
    _archive(p, **swapped)
    assert _same(load_face_model(p), model)


def test_unsigned_indices_load_and_a_damaged_compressed_archive_is_refused(tmp_path):
    """``faces`` / ``landmark_vertices`` as uint32 (a mesh library's usual index type) load (they were refused as
    "uint32, not integer values"); a damaged np.savez_compressed archive is one InputError line (zlib.error came
    out bare)."""
    model = load_candide3()
    p = tmp_path / "c.npz"
    save_face_model(model, p)
    _archive(p, faces=model.faces.numpy().astype(np.uint32), landmark_vertices=model.landmark_vertices.numpy()
             .astype(np.uint16))  # fmt: skip
    assert _same(load_face_model(p), model)
    _archive(p, faces=np.full((184, 3), 2**63 + 5, dtype=np.uint64))  # (no int64: refused as an index)
    with pytest.raises(InputError):
        load_face_model(p)
    save_face_model(model, p)
    with np.load(p, allow_pickle=False) as data:
        np.savez_compressed(tmp_path / "z.npz", **{k: data[k] for k in data.files})
    assert _same(load_face_model(tmp_path / "z.npz"), model)
    raw = bytearray((tmp_path / "z.npz").read_bytes())
    with zipfile.ZipFile(tmp_path / "z.npz") as z:
        info = z.getinfo("mean.npy")
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    raw[start : start + info.compress_size] = b"\xff" * info.compress_size  # (deflate: an invalid block type)
    (tmp_path / "z.npz").write_bytes(bytes(raw))
    with pytest.raises(InputError, match="not a torchface face model file") as info_:
        load_face_model(tmp_path / "z.npz")
    assert "\n" not in str(info_.value)
