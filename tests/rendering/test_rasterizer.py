"""Tests for torchface.rendering.rasterizer (fast path) against torchface.rendering.reference (oracle)."""

from __future__ import annotations

import pytest
import torch
import trimesh

import torchface.rendering.rasterizer as rasterizer_module
from torchface import _native
from torchface.backend import Backend
from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry.camera import Intrinsics
from torchface.rendering import Fragments, rasterize, rasterize_coverage, rasterize_reference

CAM = Intrinsics.default(32, 24)
EDGE_TOL = 1e-6


@pytest.fixture(autouse=True, params=["boxes", "spans", "native"])
def candidate_path(request, monkeypatch):
    """Every test runs with both of the torch code's ways of finding candidate pixels, whole bounding boxes (what
    the small images here get by default) and scanline spans (what larger images get), and with the native
    z-buffer (``torchface/_native/coverage.h``, the default where it can run)."""
    if request.param == "native":
        if _native.library() is None:
            pytest.skip(f"native kernels unavailable: {_native.unavailable_reason()}")
        return request.param
    monkeypatch.setattr(rasterizer_module, "use_native", lambda *args, **kwargs: False)
    limit = 1 << 40 if request.param == "boxes" else -1
    monkeypatch.setattr(rasterizer_module, "_BBOX_MAX_PAIRS", limit)
    return request.param


def random_soup(seed: int, batch: int, num_faces: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Independent random triangles in front of the camera, overlapping in depth: ``(B, 3F, 3)``, ``(F, 3)``."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.rand(batch, num_faces, 1, 3, generator=g, dtype=torch.float64)
    centres = centres * torch.tensor([90.0, 70.0, 80.0], dtype=torch.float64) + torch.tensor(
        [-45.0, -35.0, 80.0], dtype=torch.float64
    )
    offsets = (torch.rand(batch, num_faces, 3, 3, generator=g, dtype=torch.float64) - 0.5) * 50.0
    verts = (centres + offsets).reshape(batch, num_faces * 3, 3)
    faces = torch.arange(num_faces * 3).reshape(num_faces, 3)
    return verts.to(dtype), faces


def random_surface(seed: int, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A jittered open tube (shared edges everywhere) whose opening faces the camera.

    Outward normals point away from the tube's axis, so the inside, seen through the opening, is
    back-facing, the outer lips are front-facing, and the lips hide part of the inside.
    """
    g = torch.Generator().manual_seed(seed)
    n = 8
    s = torch.linspace(-0.75 * torch.pi, 0.75 * torch.pi, n, dtype=torch.float64)
    ys = torch.linspace(-50.0, 50.0, n, dtype=torch.float64)
    gy, gs = torch.meshgrid(ys, s, indexing="ij")
    base = torch.stack([50.0 * torch.sin(gs), gy, 150.0 + 50.0 * torch.cos(gs)], -1).reshape(-1, 3)
    verts = base + (torch.rand(batch, n * n, 3, generator=g, dtype=torch.float64) - 0.5) * 6.0
    idx = torch.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = torch.cat([torch.stack([a, c, b], -1).reshape(-1, 3), torch.stack([b, c, d], -1).reshape(-1, 3)])
    return verts, faces


def icosphere(radius: float, centre: tuple[float, float, float], subdivisions: int = 2):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    verts = torch.tensor(mesh.vertices, dtype=torch.float64) + torch.tensor(centre, dtype=torch.float64)
    return verts[None], torch.tensor(mesh.faces, dtype=torch.int64), mesh


def min_bary(frag: Fragments) -> torch.Tensor:
    return frag.bary.amin(-1)


def assert_fragments_match(fast: Fragments, ref: Fragments, *, atol: float = 1e-8, max_ambiguous: float = 0.02):
    """Same triangle wherever neither result is within EDGE_TOL of an edge; same numbers where they agree."""
    fast_fg, ref_fg = fast.pix_to_face >= 0, ref.pix_to_face >= 0
    ambiguous = (fast_fg & (min_bary(fast) < EDGE_TOL)) | (ref_fg & (min_bary(ref) < EDGE_TOL))
    assert ambiguous.double().mean() <= max_ambiguous
    same = fast.pix_to_face == ref.pix_to_face
    assert same[~ambiguous].all(), f"{int((~same & ~ambiguous).sum())} unambiguous pixels differ"
    both = same & fast_fg
    torch.testing.assert_close(fast.bary[both].double(), ref.bary[both].double(), atol=atol, rtol=0)
    torch.testing.assert_close(fast.zbuf[both].double(), ref.zbuf[both].double(), atol=0, rtol=atol)
    assert torch.equal(fast.facing[same], ref.facing[same])
    assert torch.isinf(fast.zbuf[~fast_fg]).all() and (fast.bary[~fast_fg] == 0).all()
    assert (fast.facing[~fast_fg] == 0).all()


# --------------------------------------------------------------------------------------------- smoke, shapes


def test_cardinality_and_dtypes():
    verts, faces = random_soup(0, 2, 5, torch.float32)
    frag = rasterize(verts, faces, CAM)
    assert frag.pix_to_face.shape == (2, 24, 32) and frag.pix_to_face.dtype == torch.int64
    assert frag.bary.shape == (2, 24, 32, 3) and frag.bary.dtype == torch.float32
    assert frag.zbuf.shape == (2, 24, 32) and frag.zbuf.dtype == torch.float32
    assert frag.facing.shape == (2, 24, 32) and frag.facing.dtype == torch.int8
    fg = frag.foreground
    assert fg.any() and (~fg).any()
    torch.testing.assert_close(frag.bary[fg].sum(-1), torch.ones(int(fg.sum())))
    assert (frag.bary[fg] >= 0).all()


@pytest.mark.parametrize(
    ("verts", "faces", "error"),
    [
        (torch.zeros(4, 3), torch.tensor([[0, 1, 2]]), ValueError),
        (torch.zeros(1, 4, 2), torch.tensor([[0, 1, 2]]), ValueError),
        (torch.zeros(1, 4, 3, dtype=torch.int64), torch.tensor([[0, 1, 2]]), TypeError),
        (torch.zeros(1, 4, 3), torch.tensor([0, 1, 2]), ValueError),
        (torch.zeros(1, 4, 3), torch.tensor([[0.0, 1.0, 2.0]]), TypeError),
        (torch.zeros(1, 4, 3), torch.tensor([[0, 1, 4]]), ValueError),
        (torch.zeros(1, 4, 3), torch.tensor([[0, -1, 2]]), ValueError),
    ],
)
def test_exceptions(verts, faces, error):
    with pytest.raises(error):
        rasterize(verts, faces, CAM)


class _HostReads(torch.overrides.TorchFunctionMode):
    """Counts the reads of tensor values on the host (``bool``, ``int``, ``float``, ``item``, ``tolist``): each
    waits for the device (on a GPU, a synchronisation)."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if getattr(func, "__name__", "") in ("__bool__", "__int__", "__float__", "__index__", "item", "tolist"):
            self.count += 1
        return func(*args, **(kwargs or {}))


def test_the_face_index_check_reads_a_face_tensor_once_and_again_after_it_changed():
    """The check that faces index the vertices reads the faces' index range on the host once per face tensor (it
    was read twice at every rasterization, the tracker's two a frame included); an in-place change of the faces is
    still caught (the tensor's version counter), as is another tensor."""
    verts, faces = random_soup(0, 1, 3)
    faces = faces.clone()
    rasterize(verts, faces, CAM)
    with _HostReads() as reads:
        rasterizer_module._check_mesh(verts, faces)
        rasterizer_module._check_mesh(verts, faces)
    assert reads.count == 0
    faces[0, 1] = verts.shape[1]  # in place: one past the last vertex
    with pytest.raises(ValueError, match="faces must index the 9 vertices"):
        rasterize(verts, faces, CAM)
    faces[0, 1] = 0
    rasterize(verts, faces, CAM)
    with pytest.raises(ValueError, match="got indices in \\[-1, "):
        rasterize(verts, torch.where(faces == 0, -1, faces), CAM)


def test_the_face_index_check_sees_faces_given_other_values_through_data():
    """``faces.data = other`` gives the same tensor (object) other values and keeps its version counter: the cached
    index range was handed back, and faces one past the last vertex reached the gather (an IndexError on the CPU, a
    device-side assert on a GPU) instead of the check's ValueError."""
    verts, faces = random_soup(0, 1, 3)
    faces = faces.clone()
    rasterize(verts, faces, CAM)
    faces.data = torch.where(faces == faces.max(), verts.shape[1], faces)
    with pytest.raises(ValueError, match="faces must index the 9 vertices"):
        rasterize(verts, faces, CAM)


def test_the_face_index_check_reads_again_after_a_change_made_while_it_read(monkeypatch):
    """A change of the faces made while the check read their range (another thread's; here right after the read)
    is read at the next check: the version counter kept with the range is the one from before the read (the one
    after it was kept, and the range read before the change was handed back from then on)."""
    verts, faces = random_soup(0, 1, 3)
    faces = faces.clone()
    tolist = torch.Tensor.tolist

    def tolist_then_change(self: torch.Tensor):
        values = tolist(self)
        faces[0, 1] = verts.shape[1]  # in place: one past the last vertex
        return values

    monkeypatch.setattr(torch.Tensor, "tolist", tolist_then_change)
    rasterizer_module._check_mesh(verts, faces)  # the range read before the change: in range
    monkeypatch.setattr(torch.Tensor, "tolist", tolist)
    with pytest.raises(ValueError, match="faces must index the 9 vertices"):
        rasterizer_module._check_mesh(verts, faces)


def test_the_face_index_check_under_a_torch_func_transform():
    """Faces passed through a ``torch.func`` transform are wrappers without memory: the check reads their range
    without caching it (its stamp, which reads the memory's address, failed: "Cannot access data pointer of Tensor
    that doesn't have storage"), and still refuses an index one past the last vertex."""
    verts, faces = random_soup(0, 1, 3)

    def depth(v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        return torch.nan_to_num(rasterize(v, f, CAM).zbuf, posinf=0.0).sum()

    grad = torch.func.grad(depth)(verts, faces)
    torch.testing.assert_close(grad, torch.autograd.grad(depth(verts.requires_grad_(), faces), verts)[0])
    with pytest.raises(ValueError, match="faces must index the 9 vertices"):
        torch.func.grad(depth)(verts.detach(), torch.where(faces == faces.max(), verts.shape[1], faces))


def test_empty_mesh_and_empty_batch():
    frag = rasterize(torch.rand(2, 4, 3) + 1.0, torch.zeros(0, 3, dtype=torch.int64), CAM)
    assert (frag.pix_to_face == -1).all() and torch.isinf(frag.zbuf).all() and frag.bary.shape == (2, 24, 32, 3)
    assert rasterize(torch.rand(0, 4, 3), torch.tensor([[0, 1, 2]]), CAM).pix_to_face.shape == (0, 24, 32)


def test_exception_intrinsics_and_near():
    verts, faces = random_soup(0, 1, 2)
    with pytest.raises(TypeError):
        rasterize(verts, faces, (32, 24))
    for near in (0.0, float("inf"), float("nan")):  # (inf passed "> 0": every triangle cut)
        for raster in (rasterize, rasterize_coverage):
            with pytest.raises(ValueError, match=r"^near must be a finite number > 0 \(millimetres\), got"):
                raster(verts, faces, CAM, near=near)


def test_exception_option_types():
    """A near of another type was "'<' not supported between instances of 'int' and 'str'" (rasterize) or not
    looked at (rasterize_reference: a NaN near gave an empty image); cull_backfaces="no" was taken as true, and
    culled; rasterize_reference met another camera type with "no attribute". Each is now check_number's,
    check_bool's or the intrinsics' error, naming the argument."""
    verts, faces = random_soup(0, 1, 2)
    for raster in (rasterize, rasterize_coverage, rasterize_reference):
        with pytest.raises(TypeError, match=r"^near must be a real number, got str '1'"):
            raster(verts, faces, CAM, near="1")  # type: ignore[arg-type]
        with pytest.raises(TypeError, match=r"^near must be a real number, got NoneType"):
            raster(verts, faces, CAM, near=None)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match=r"^cull_backfaces must be a bool, got str 'no'"):
            raster(verts, faces, CAM, cull_backfaces="no")  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="^intrinsics must be an Intrinsics, got tuple"):
            raster(verts, faces, (32, 24))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^near must be a finite number > 0 \(millimetres\), got nan"):
        rasterize_reference(verts, faces, CAM, near=float("nan"))
    # numbers of other types than float are still taken as the numbers they are
    assert torch.equal(rasterize(verts, faces, CAM, near=1).pix_to_face, rasterize(verts, faces, CAM).pix_to_face)


# ----------------------------------------------------------------------------------------- fast vs reference


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_matches_reference_random_soup(seed):
    verts, faces = random_soup(seed, 3 if seed % 2 else 2, 20)
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert (ref.pix_to_face >= 0).double().mean() > 0.2
    assert_fragments_match(fast, ref)


def test_matches_reference_slivers():
    # Long thin triangles (nearly horizontal, vertical and diagonal) stress the scanline spans.
    g = torch.Generator().manual_seed(42)
    num = 40
    start = (torch.rand(2, num, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([80.0, 60.0, 20.0])
    start = start + torch.tensor([0.0, 0.0, 100.0])
    direction = torch.randn(2, num, 3, generator=g, dtype=torch.float64)
    direction[:, : num // 3, 1] *= 1e-3  # nearly horizontal in the image
    direction[:, num // 3 : 2 * num // 3, 0] *= 1e-3  # nearly vertical
    end = start + 60.0 * direction / direction.norm(dim=-1, keepdim=True)
    side = torch.randn(2, num, 3, generator=g, dtype=torch.float64) * 1.5
    third = (start + end) / 2 + side
    verts = torch.stack([start, end, third], 2).reshape(2, -1, 3)
    faces = torch.arange(3 * num).reshape(num, 3)
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert ref.foreground.sum() > 50
    assert_fragments_match(fast, ref, max_ambiguous=0.05)


@pytest.mark.parametrize("seed", [10, 11])
def test_matches_reference_folded_surface(seed):
    verts, faces = random_surface(seed, 2)
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert (ref.facing == -1).any() and (ref.facing == 1).any()
    assert_fragments_match(fast, ref)
    culled_fast = rasterize(verts, faces, CAM, cull_backfaces=True)
    culled_ref = rasterize_reference(verts, faces, CAM, cull_backfaces=True)
    assert_fragments_match(culled_fast, culled_ref)
    assert (culled_fast.facing != -1).all()


def test_matches_reference_sphere_and_perspective_bary():
    verts, faces, _ = icosphere(60.0, (10.0, -5.0, 150.0))
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert_fragments_match(fast, ref)
    # Perspective-correct: barycentric interpolation of the corners lands on the pixel's ray at zbuf.
    fg = fast.foreground[0]
    tri = verts[0][faces[fast.pix_to_face[0][fg]]]
    point = (fast.bary[0][fg].unsqueeze(-1) * tri).sum(-2)
    ys, xs = fg.nonzero().unbind(-1)
    torch.testing.assert_close(point[:, 2], fast.zbuf[0][fg])
    torch.testing.assert_close(point[:, 0] / point[:, 2] * CAM.fx + CAM.cx, xs.double())
    torch.testing.assert_close(point[:, 1] / point[:, 2] * CAM.fy + CAM.cy, ys.double())


# ------------------------------------------------------------------------------------------------ edge cases


def test_triangle_partly_behind_camera():
    # One vertex behind the camera; the visible part spans a region no projected bbox could describe.
    verts = torch.tensor([[[-30.0, -20.0, 100.0], [30.0, -20.0, 100.0], [0.0, 40.0, -20.0]]], dtype=torch.float64)
    faces = torch.tensor([[0, 2, 1]])
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert 0 < int(ref.foreground.sum()) < 24 * 32
    assert_fragments_match(fast, ref)
    assert (fast.zbuf[fast.foreground] > 1.0).all()


def test_near_plane_and_huge_projections():
    # A tilted triangle cut by a custom near plane, and one whose corner is just beyond the default
    # near plane so that it projects tens of thousands of pixels away (whole-row candidate path).
    tilted = torch.tensor([[-40.0, -30.0, 60.0], [40.0, -30.0, 60.0], [0.0, 40.0, 140.0]], dtype=torch.float64)
    close = torch.tensor([[-400.0, 2.0, 1.05], [30.0, -20.0, 80.0], [35.0, 25.0, 90.0]], dtype=torch.float64)
    verts = torch.stack([tilted, close])
    faces = torch.tensor([[0, 2, 1]])
    for near in (1.0, 90.0):
        fast = rasterize(verts, faces, CAM, near=near)
        ref = rasterize_reference(verts, faces, CAM, near=near)
        assert fast.foreground[0].any()
        assert_fragments_match(fast, ref)
        assert (fast.zbuf[fast.foreground] > near).all()
    cut = rasterize(verts, faces, CAM, near=90.0).foreground[0]
    assert cut.sum() < rasterize(verts, faces, CAM).foreground[0].sum()


def test_triangle_fully_behind_or_offscreen():
    # Behind the camera: would project into the image if the sign of Z were ignored.
    behind = torch.tensor([[-40.0, -30.0, -60.0], [40.0, -30.0, -60.0], [0.0, 40.0, -60.0]], dtype=torch.float64)
    offscreen = torch.tensor([[400.0, 0.0, 100.0], [500.0, 0.0, 100.0], [450.0, 60.0, 100.0]], dtype=torch.float64)
    within_near = torch.tensor([[-40.0, -30.0, 0.5], [40.0, -30.0, 0.5], [0.0, 40.0, 0.9]], dtype=torch.float64)
    verts = torch.cat([behind, offscreen, within_near])[None]
    faces = torch.tensor([[0, 1, 2], [0, 2, 1], [3, 4, 5], [3, 5, 4], [6, 7, 8], [6, 8, 7]])
    for fn in (rasterize, rasterize_reference):
        frag = fn(verts, faces, CAM)
        assert not frag.foreground.any()


def test_degenerate_triangles_produce_nothing():
    verts = torch.tensor(
        [[
            [-40.0, -30.0, 100.0], [0.0, 0.0, 100.0], [40.0, 30.0, 100.0],  # collinear
            [-40.0, 30.0, 90.0], [40.0, -30.0, 90.0],  # with vertex 3 repeated: zero area
            [-50.0, -50.0, 120.0], [50.0, -50.0, 120.0], [0.0, 50.0, 120.0],  # an ordinary triangle
        ]],
        dtype=torch.float64,
    )  # fmt: skip
    faces = torch.tensor([[0, 1, 2], [3, 4, 3], [3, 3, 3], [5, 7, 6]])
    for dtype in (torch.float64, torch.float32):
        fast = rasterize(verts.to(dtype), faces, CAM)
        ref = rasterize_reference(verts.to(dtype), faces, CAM)
        assert set(fast.pix_to_face.unique().tolist()) == {-1, 3}
        assert_fragments_match(fast, ref, atol=1e-5)
        alone = rasterize(verts.to(dtype), faces[3:], CAM)
        assert torch.equal(alone.pix_to_face >= 0, fast.pix_to_face >= 0)


def test_exact_depth_ties_lowest_index_wins():
    # Face 1 duplicates face 3 (bit-identical arithmetic); faces 0 and 2 are different triangles in
    # the same fronto-parallel plane z = 100 overlapping each other (integer coordinates: exact depths).
    verts = torch.tensor(
        [[
            [-60.0, -40.0, 100.0], [40.0, -40.0, 100.0], [40.0, 40.0, 100.0],
            [60.0, 40.0, 100.0], [-40.0, 40.0, 100.0], [60.0, -40.0, 100.0],
            [-30.0, -30.0, 80.0], [30.0, -30.0, 80.0], [0.0, 30.0, 80.0],
        ]],
        dtype=torch.float64,
    )  # fmt: skip
    faces = torch.tensor([[3, 5, 4], [6, 8, 7], [0, 2, 1], [6, 8, 7]])
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert torch.equal(fast.pix_to_face, ref.pix_to_face)
    seen = set(fast.pix_to_face.unique().tolist())
    assert 3 not in seen and {0, 1, 2} <= seen
    # Where the plane triangles overlap (and the nearer one does not cover), face 0 beats face 2.
    only_plane = rasterize(verts, faces[[0, 2]], CAM)
    both = rasterize(verts, faces[[0]], CAM).foreground & rasterize(verts, faces[[2]], CAM).foreground
    assert both.any() and (only_plane.pix_to_face[both] == 0).all()
    for dtype in (torch.float32, torch.float64):
        frag = rasterize(verts.to(dtype), faces, CAM)
        assert torch.equal(frag.pix_to_face, fast.pix_to_face)


def test_tiny_subpixel_triangles():
    # Project a 0.3 px triangle around pixel centre (10, 7) and one between pixel centres.
    def around(u: float, v: float, z: float = 100.0) -> torch.Tensor:
        pts = torch.tensor([[u - 0.15, v - 0.1], [u + 0.15, v - 0.1], [u, v + 0.2]], dtype=torch.float64)
        xy = (pts - torch.tensor([CAM.cx, CAM.cy], dtype=torch.float64)) / CAM.fx * z
        return torch.cat([xy, torch.full((3, 1), z, dtype=torch.float64)], -1)

    verts = torch.cat([around(10.0, 7.0), around(20.5, 15.5)])[None]
    faces = torch.tensor([[0, 2, 1], [3, 5, 4]])
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert fast.foreground.sum() == 1 and fast.pix_to_face[0, 7, 10] == 0
    assert torch.equal(fast.pix_to_face, ref.pix_to_face)
    torch.testing.assert_close(fast.bary, ref.bary)


def test_huge_triangles_cover_the_image():
    big = torch.tensor([[-1e4, -1e4, 428.0], [1e4, -1e4, 428.0], [0.0, 1e4, 428.0]], dtype=torch.float64)
    # A second huge one, tilted through the near plane, crossing the first inside the image.
    tilted = torch.tensor([[-5e3, -5e3, -50.0], [5e3, -5e3, -50.0], [0.0, 5e3, 900.0]], dtype=torch.float64)
    verts = torch.cat([big, tilted])[None]
    faces = torch.tensor([[0, 2, 1], [3, 5, 4]])
    fast = rasterize(verts, faces, CAM)
    ref = rasterize_reference(verts, faces, CAM)
    assert fast.foreground.all()
    assert set(fast.pix_to_face.unique().tolist()) == {0, 1}
    assert_fragments_match(fast, ref)


# -------------------------------------------------------------------------------------- batching, culling


def test_batched_equals_per_sample():
    verts, faces = random_soup(5, 3, 10)
    batched = rasterize(verts, faces, CAM)
    for b in range(3):
        single = rasterize(verts[b : b + 1], faces, CAM)
        assert torch.equal(single.pix_to_face[0], batched.pix_to_face[b])
        assert torch.equal(single.bary[0], batched.bary[b])
        assert torch.equal(single.zbuf[0], batched.zbuf[b])
        assert torch.equal(single.facing[0], batched.facing[b])


def test_chunking_gives_identical_result(monkeypatch):
    verts, faces = random_surface(3, 2)
    whole = rasterize(verts, faces, CAM)
    monkeypatch.setattr(rasterizer_module, "_MAX_PAIRS_PER_CHUNK", 37)
    chunked = rasterize(verts, faces, CAM)
    for name in ("pix_to_face", "bary", "zbuf", "facing"):
        assert torch.equal(getattr(whole, name), getattr(chunked, name))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_boxes_and_spans_give_identical_fragments(monkeypatch, dtype):
    # The two candidate paths differ only in which pixels they test; the test and its arithmetic are the same.
    near_plane = torch.tensor([[[-30.0, -20.0, -10.0], [40.0, -20.0, 90.0], [0.0, 40.0, 90.0]]], dtype=torch.float64)
    meshes = [random_soup(8, 2, 30), random_surface(9, 2), (near_plane, torch.tensor([[0, 1, 2]]))]
    cam = Intrinsics.default(160, 120)
    for verts, faces in meshes:
        out = {}
        for path, limit in (("boxes", 1 << 40), ("spans", -1)):
            monkeypatch.setattr(rasterizer_module, "_BBOX_MAX_PAIRS", limit)
            out[path] = rasterize(verts.to(dtype), faces, cam)
        assert (out["spans"].pix_to_face >= 0).any()
        for name in ("pix_to_face", "bary", "zbuf", "facing"):
            assert torch.equal(getattr(out["boxes"], name), getattr(out["spans"], name)), name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_scanline_spans_lose_no_pixel(monkeypatch, dtype):
    # The spans only prune candidates: testing every triangle on every pixel gives identical fragments.
    meshes = [random_soup(8, 2, 30, dtype), random_surface(9, 2)]
    pruned = [rasterize(v.to(dtype), f, CAM) for v, f in meshes]
    monkeypatch.setattr(rasterizer_module, "_MAX_PROJECTED_PX", -1.0)  # every triangle takes whole rows
    for (v, f), expected in zip(meshes, pruned):
        full = rasterize(v.to(dtype), f, CAM)
        for name in ("pix_to_face", "bary", "zbuf", "facing"):
            assert torch.equal(getattr(full, name), getattr(expected, name))


def test_facing_values_and_culling():
    tri = torch.tensor([[-50.0, -50.0, 100.0], [50.0, -50.0, 100.0], [0.0, 50.0, 100.0]], dtype=torch.float64)
    verts = tri[None]
    front_faces, back_faces = torch.tensor([[0, 2, 1]]), torch.tensor([[0, 1, 2]])
    front = rasterize(verts, front_faces, CAM)
    back = rasterize(verts, back_faces, CAM)
    assert torch.equal(front.foreground, back.foreground) and front.foreground.any()
    assert (front.facing[front.foreground] == 1).all() and (back.facing[back.foreground] == -1).all()
    assert (front.facing[~front.foreground] == 0).all()
    assert not rasterize(verts, back_faces, CAM, cull_backfaces=True).foreground.any()
    assert torch.equal(rasterize(verts, front_faces, CAM, cull_backfaces=True).pix_to_face, front.pix_to_face)
    # A closed mesh: back faces are always hidden behind front faces, so culling changes nothing.
    sphere, sphere_faces, _ = icosphere(50.0, (0.0, 0.0, 180.0))
    plain = rasterize(sphere, sphere_faces, CAM)
    culled = rasterize(sphere, sphere_faces, CAM, cull_backfaces=True)
    assert torch.equal(plain.pix_to_face, culled.pix_to_face)
    assert (plain.facing[plain.foreground] == 1).all()


def test_float32_agrees_with_float64():
    verts, faces = random_surface(7, 2)
    f64 = rasterize(verts, faces, CAM)
    f32 = rasterize(verts.float(), faces, CAM)
    fg64, fg32 = f64.foreground, f32.foreground
    ambiguous = (fg64 & (min_bary(f64) < 1e-4)) | (fg32 & (min_bary(f32).double() < 1e-4))
    same = f64.pix_to_face == f32.pix_to_face
    assert same[~ambiguous].all() and ambiguous.double().mean() < 0.02
    both = same & fg64
    torch.testing.assert_close(f32.bary[both].double(), f64.bary[both], atol=1e-4, rtol=0)
    torch.testing.assert_close(f32.zbuf[both].double(), f64.zbuf[both], atol=0, rtol=1e-5)


@pytest.mark.parametrize("scale", [1e8, 1e12, 1e20, 1e30])
def test_float32_far_meshes_are_the_near_meshes_scaled(scale):
    """A mesh scaled by ``s`` (the same image) gives the same triangles and coordinates and ``s`` times the depths.
    In float32 every triangle with coordinates beyond about 3e8 mm was dropped as edge-on (its squared normal
    overflowed to inf: nothing at all was seen at 1e10 mm), and ``n . v0`` overflowed from about 1e12 mm."""
    verts, faces = random_surface(7, 2)
    near = rasterize(verts, faces, CAM)
    far_verts = (verts * scale).float().requires_grad_(True)
    far = rasterize(far_verts, faces, CAM)
    fg, fg32 = near.foreground, far.foreground
    assert fg.any()
    ambiguous = (fg & (min_bary(near) < 1e-4)) | (fg32 & (min_bary(far).double() < 1e-4))
    same = near.pix_to_face == far.pix_to_face
    assert same[~ambiguous].all() and ambiguous.double().mean() < 0.02
    both = same & fg
    torch.testing.assert_close(far.bary[both].double(), near.bary[both], atol=1e-4, rtol=0)
    torch.testing.assert_close(far.zbuf[both].double() / scale, near.zbuf[both], atol=0, rtol=1e-5)
    # Gradients: finite, and those of the near mesh divided by s (the coordinates are scale-free).
    near_verts = verts.float().requires_grad_(True)
    w = torch.rand(both.shape + (3,), generator=torch.Generator().manual_seed(0))
    (g_far,) = torch.autograd.grad((far.bary * w)[both].sum(), far_verts)
    near32 = rasterize(near_verts, faces, CAM)
    (g_near,) = torch.autograd.grad((near32.bary * w)[both].sum(), near_verts)
    assert bool(torch.isfinite(g_far).all())
    torch.testing.assert_close(g_far.double() * scale, g_near.double(), atol=1e-4 * float(g_near.abs().max()), rtol=1e-3)


def test_float16_meshes_in_millimetres_are_rasterized():
    """In float16 (largest value 65504) the squared normal of any triangle more than a few millimetres across
    overflowed, and every triangle of a face-sized mesh was dropped as edge-on: its corners are now scaled by a power
    of two first (as a float32 mesh beyond 2.7e8 mm), and the fragments are float32's (away from edges)."""
    verts, faces = random_surface(7, 2)
    f32 = rasterize(verts.float(), faces, CAM)
    f16 = rasterize(verts.half(), faces, CAM)
    assert f16.foreground.any()
    ambiguous = (f32.foreground & (min_bary(f32) < 1e-2)) | (f16.foreground & (min_bary(f16).float() < 1e-2))
    assert ambiguous.double().mean() < 0.2
    assert torch.equal(f16.pix_to_face[~ambiguous], f32.pix_to_face[~ambiguous])
    both = (f16.pix_to_face == f32.pix_to_face) & f32.foreground
    torch.testing.assert_close(f16.zbuf[both].float(), f32.zbuf[both], atol=0, rtol=1e-2)  # float16: eps 1e-3


# ------------------------------------------------------------------------------------------------ gradients


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cull", [False, True])
def test_coverage_evaluates_rasterize_fragments_bit_for_bit(dtype, cull):
    # rasterize_coverage leaves the barycentric coordinates and depths to be evaluated where asked; wherever
    # that is (covered or background pixels, all pixels, a part of the batch), they are rasterize's exactly.
    for verts, faces in (random_soup(12, 3, 25), random_surface(13, 3)):
        verts = verts.to(dtype)
        full = rasterize(verts, faces, CAM, cull_backfaces=cull)
        cov = rasterize_coverage(verts, faces, CAM, cull_backfaces=cull)
        assert torch.equal(cov.pix_to_face, full.pix_to_face) and torch.equal(cov.facing, full.facing)
        every = cov.fragments()
        for name in ("pix_to_face", "bary", "zbuf", "facing"):
            assert torch.equal(getattr(every, name), getattr(full, name)), name
        g = torch.Generator().manual_seed(0)
        b, y, x = (torch.randint(0, n, (500,), generator=g) for n in (3, CAM.height, CAM.width))
        covered = full.pix_to_face[b, y, x] >= 0
        assert covered.any() and (~covered).any()
        assert torch.equal(cov.barycentrics(b, y, x), full.bary[b, y, x])
        face = full.pix_to_face[b, y, x][covered]
        got = cov.covered_barycentrics(b[covered], face, y[covered], x[covered])
        assert torch.equal(got, full.bary[b, y, x][covered])
        got, depth = cov.covered_depths(b[covered], face, y[covered], x[covered])
        assert torch.equal(got, full.bary[b, y, x][covered]) and torch.equal(depth, full.zbuf[b, y, x][covered])
        # A part: samples 1..2, the top-left 20 x 30 pixels, indexed from its own origin.
        part = cov.part(slice(1, 3), 20, 30)
        assert torch.equal(part.pix_to_face, full.pix_to_face[1:3, :20, :30])
        for name in ("bary", "zbuf", "facing"):
            assert torch.equal(getattr(part.fragments(), name), getattr(full, name)[1:3, :20, :30]), name
        inside = (b >= 1) & (y < 20) & (x < 30)
        assert torch.equal(part.barycentrics(b[inside] - 1, y[inside], x[inside]), full.bary[b, y, x][inside])


def test_coverage_barycentrics_are_differentiable():
    verts = torch.tensor(
        [[[-47.3, -41.1, 95.0], [52.2, -38.7, 110.0], [3.1, 49.4, 120.0]]], dtype=torch.float64, requires_grad=True
    )
    faces = torch.tensor([[0, 2, 1]])
    cam = Intrinsics.default(12, 9)
    at = rasterize(verts, faces, cam).foreground[0].nonzero()
    b = torch.zeros(at.shape[0], dtype=torch.int64)

    def fn(v):
        return rasterize_coverage(v, faces, cam).barycentrics(b, at[:, 0], at[:, 1])

    assert torch.autograd.gradcheck(fn, (verts,), eps=1e-6, atol=1e-6)


def test_gradcheck_bary_and_depth():
    verts = torch.tensor(
        [[[-47.3, -41.1, 95.0], [52.2, -38.7, 110.0], [3.1, 49.4, 120.0]]], dtype=torch.float64, requires_grad=True
    )
    faces = torch.tensor([[0, 2, 1]])
    cam = Intrinsics.default(12, 9)
    mask = rasterize(verts, faces, cam).foreground
    assert mask.any() and min_bary(rasterize(verts, faces, cam))[mask].min() > 1e-5

    def fn(v):
        frag = rasterize(v, faces, cam)
        assert torch.equal(frag.foreground, mask)
        return frag.bary[mask], frag.zbuf[mask]

    assert torch.autograd.gradcheck(fn, (verts,), eps=1e-6, atol=1e-6)


def test_a_triangle_with_a_nan_corner_gives_its_shared_vertices_no_nan_gradient():
    """A triangle with a NaN corner produces no fragment, and the vertices it shares with visible triangles get
    the gradient they get without it (they used to get NaN: a zero gradient times its NaN coefficients)."""
    cam = Intrinsics.default(8, 6, focal=8.0)
    faces = torch.tensor([[0, 2, 1], [0, 1, 3]])
    for backend in (Backend.TORCH, Backend.AUTO):
        v = torch.tensor([[[-5.0, -4, 10], [6, -3, 11], [0, 5, 12], [1, 1, float("nan")]]], requires_grad=True)
        frag = rasterize(v, faces, cam, backend=backend)
        assert bool((frag.pix_to_face[frag.foreground] == 0).all())
        frag.zbuf[frag.foreground].sum().backward()
        alone = v.detach()[:, :3].clone().requires_grad_(True)
        ref = rasterize(alone, faces[:1], cam, backend=backend)
        ref.zbuf[ref.foreground].sum().backward()
        torch.testing.assert_close(v.grad[0, :3], alone.grad[0], rtol=0, atol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    verts, faces = random_surface(4, 2)
    cpu = rasterize(verts.float(), faces, CAM)
    gpu = rasterize(verts.float().cuda(), faces.cuda(), CAM)
    assert torch.equal(cpu.pix_to_face, gpu.pix_to_face.cpu())
    torch.testing.assert_close(cpu.bary, gpu.bary.cpu(), atol=1e-5, rtol=0)


def _candide_at_random_poses(model, n: int, g: torch.Generator, near_first: bool = False) -> torch.Tensor:
    """``(n, V, 3)`` float64 camera-frame vertices of ``model``'s mean face at ``n`` random poses drawn from ``g``
    (yaw, pitch, roll within +-90, 45, 30 degrees, turned away too; 450 mm +-150 mm each way); with ``near_first``
    the first 30 mm from the camera, its triangles crossing the near plane."""
    from torchface.geometry.so3 import euler_to_matrix

    ypr = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([180.0, 90.0, 60.0])
    t = torch.tensor([0.0, 0.0, 450.0]) + (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 300.0
    if near_first:
        t[0, 2] = 30.0
    return model.mean @ euler_to_matrix(ypr).mT + t[:, None]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_coverage_is_the_torch_codes_bit_for_bit(candidate_path, monkeypatch, dtype):
    """The native z-buffer tests every pixel of each box with the torch code's arithmetic: the same fragments bit
    for bit as either torch path, on random soups and surfaces, triangles crossing the near plane, and the
    CANDIDE-3 mesh at random poses (turned away, close to the camera, partly off the image), a triangle projected
    far beyond the image, with and without back-face culling (the kernel makes each triangle's pixel box itself).
    Its coverage made in a caller's memory (``scratch``, holding stale values) is the same: the kernel writes every
    element there."""
    if candidate_path != "native":
        pytest.skip("compares the native path with the torch paths itself")
    from torchface.model.candide import load_candide3

    model = load_candide3(dtype=torch.float64)
    face = _candide_at_random_poses(model, 6, torch.Generator().manual_seed(5), near_first=True)
    near_plane = torch.tensor([[[-30.0, -20.0, -10.0], [40.0, -20.0, 90.0], [0.0, 40.0, 90.0]]], dtype=torch.float64)
    # A corner projected beyond _MAX_PROJECTED_PX (the kernel's own boxes: whole image rows, as the torch code's)
    far = torch.tensor([[[-30.0, -20.0, 100.0], [1e5, -20.0, 100.0], [0.0, 40.0, 100.0]]], dtype=torch.float64)
    tri = torch.tensor([[0, 1, 2]])
    meshes = [random_soup(8, 2, 30), random_surface(9, 2), (near_plane, tri), (far, tri), (face, model.faces)]
    for verts, faces in meshes:
        covered = False
        for cam in (CAM, Intrinsics.default(160, 120), Intrinsics.default(320, 240)):
            for cull in (False, True):
                native = rasterize(verts.to(dtype), faces, cam, cull_backfaces=cull, backend=Backend.NATIVE)
                covered |= bool((native.pix_to_face >= 0).any())
                held = {}

                def scratch(name, shape, dt):
                    held[name] = torch.full(shape, 7, dtype=dt)  # (7: a face index, front-facing, depth 7 mm)
                    return held[name]

                cov = rasterizer_module._cover(verts.to(dtype), faces, cam, cull, NEAR_PLANE_MM, Backend.NATIVE,
                                               pixels=False, scratch=scratch)[0]  # fmt: skip
                assert sorted(held) == ["depth", "facing", "pix_to_face"]
                assert cov.pix_to_face.data_ptr() == held["pix_to_face"].data_ptr()
                assert torch.equal(cov.pix_to_face, native.pix_to_face) and torch.equal(cov.facing, native.facing)
                for path, limit in (("boxes", 1 << 40), ("spans", -1)):
                    monkeypatch.setattr(rasterizer_module, "_BBOX_MAX_PAIRS", limit)
                    ref = rasterize(verts.to(dtype), faces, cam, cull_backfaces=cull, backend=Backend.TORCH)
                    for name in ("pix_to_face", "bary", "zbuf", "facing"):
                        assert torch.equal(getattr(native, name), getattr(ref, name)), (name, path, cull)
        assert covered  # the mesh is seen (so equality says something)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_window_coverage_is_each_windows_part_of_the_canvas(candidate_path, dtype):
    """_cover_windows (a pyramid's levels stacked on their finest level's canvas): the native kernel tests and
    stores each sample's window alone; every group's coverage is the whole canvas's part there, bit for bit
    (triangles, facing, and the fragments evaluated from it), as the torch code gives it, with the meshes reaching
    beyond the smaller windows, culled or not; each group's tensors are contiguous."""
    if candidate_path != "native":
        pytest.skip("compares the native path with the torch paths itself")
    from torchface.geometry.so3 import euler_to_matrix
    from torchface.model.candide import load_candide3
    from torchface.rendering.rasterizer import _cover_windows

    model = load_candide3(dtype=dtype)
    g = torch.Generator().manual_seed(3)
    ypr = ((torch.rand(7, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([120.0, 60.0, 40.0])).to(dtype)
    t = (torch.tensor([0.0, 0.0, 300.0]) + (torch.rand(7, 3, generator=g, dtype=torch.float64) - 0.5) * 80.0).to(dtype)
    verts = model.mean @ euler_to_matrix(ypr).mT + t[:, None]
    canvas = Intrinsics.default(96, 80)
    windows = [(3, 80, 96), (2, 40, 47), (1, 19, 25), (1, 1, 1)]
    for cull in (False, True):
        whole = rasterize_coverage(verts, model.faces, canvas, cull_backfaces=cull, backend=Backend.TORCH)
        parts = _cover_windows(verts, model.faces, canvas, windows, cull_backfaces=cull, backend=Backend.NATIVE)
        start = 0
        for (n, h, w), part in zip(windows, parts):
            want = whole.part(slice(start, start + n), h, w)
            assert part.pix_to_face.shape == (n, h, w) and part.pix_to_face.is_contiguous()
            assert part.facing.is_contiguous() and part.batch_offset == start
            assert torch.equal(part.pix_to_face, want.pix_to_face) and torch.equal(part.facing, want.facing)
            got, ref = part.fragments(), want.fragments()
            for name in ("pix_to_face", "bary", "zbuf", "facing"):
                assert torch.equal(getattr(got, name), getattr(ref, name)), (name, n, h, w, cull)
            start += n
        assert int((parts[1].pix_to_face >= 0).sum()) > 500  # the faces are in the windows
        assert bool((whole.pix_to_face[3:5, 40:] >= 0).any())  # and beyond the smaller ones
        torch_parts = _cover_windows(verts, model.faces, canvas, windows, cull_backfaces=cull, backend=Backend.TORCH)
        for part, other in zip(parts, torch_parts):
            assert torch.equal(part.pix_to_face, other.pix_to_face) and torch.equal(part.facing, other.facing)
    with pytest.raises(ValueError, match="windows must split the 7 samples"):
        _cover_windows(verts, model.faces, canvas, [(3, 80, 96)])
    with pytest.raises(ValueError, match="within the 80x96 canvas"):
        _cover_windows(verts, model.faces, canvas, [(7, 81, 96)])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_native_face_coefficients_are_the_torch_codes_bit_for_bit(candidate_path, dtype):
    """The native per-triangle coefficients (``torchface/_native/coverage.h``) are the torch code's bit for bit:
    table, front and usable, on random soups and the CANDIDE-3 mesh at random poses, with degenerate (zero-area,
    collinear) and non-finite triangles; a triangle beyond the large-coordinate limit sends the whole call back to
    the torch code (which scales it), and so does a gradient asked for."""
    if candidate_path != "native":
        pytest.skip("compares the native path with the torch path itself")
    from torchface.model.candide import load_candide3
    from torchface.rendering.rasterizer import _face_coefficients, _large_coordinate, _triangles

    model = load_candide3(dtype=torch.float64)
    g = torch.Generator().manual_seed(9)
    face = _triangles(_candide_at_random_poses(model, 5, g), model.faces).reshape(-1, 3, 3)
    soup = (torch.rand(4000, 3, 3, generator=g, dtype=torch.float64) - 0.5) * 200 + torch.tensor([0.0, 0.0, 100.0])
    soup[:50, 2] = soup[:50, 0]  # zero area
    soup[50:100, 2] = 2 * soup[50:100, 1] - soup[50:100, 0]  # collinear
    soup[100:150, :, 2] = 0.0  # edge-on through the camera centre
    soup[150, 1, 0] = float("nan")
    soup[151, 2, 2] = float("inf")
    soup[152:160] *= 1e-6  # tiny
    for tri in (face, soup):
        tri = tri.to(dtype)
        got = _face_coefficients(tri, native=True)
        want = _face_coefficients(tri)
        for a, b in zip(got, want):
            assert a.dtype == b.dtype and torch.equal(a, b)
    assert bool(want[2].any()) and not bool(want[2][:152].any())  # the soup: usable, and unusable degenerate rows
    big = soup.to(dtype).clone()
    big[3000] *= 4 * _large_coordinate(dtype) / 100
    got, want = _face_coefficients(big, native=True), _face_coefficients(big)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    assert float(want[0][12, 3000].abs()) > 0 and bool(want[2][3000])  # the scaled triangle, by the torch code
    v = soup[:20].to(dtype).clone().requires_grad_(True)
    coverage = rasterize_coverage(v.reshape(1, -1, 3), torch.arange(60).reshape(20, 3), Intrinsics.default(64, 48),
                                  backend=Backend.NATIVE)  # fmt: skip
    assert coverage.coefficients.requires_grad


@pytest.mark.parametrize("backend", [Backend.AUTO, Backend.NATIVE])
def test_forward_ad_tangents_are_the_torch_codes(candidate_path, backend):
    """Vertices that are a forward-AD dual tensor give ``zbuf`` and ``bary`` the torch code's tangents with every
    backend (the native coefficients, taken for vertices that do not require grad, dropped the tangent: None)."""
    import torch.autograd.forward_ad as fwAD

    if candidate_path != "native":
        pytest.skip("compares the native path with the torch path itself")
    verts, faces = random_surface(3, 2)
    cam = Intrinsics.default(40, 30)
    tangent = torch.randn(verts.shape, generator=torch.Generator().manual_seed(1), dtype=verts.dtype)
    out = {}
    for b in (Backend.TORCH, backend):
        with fwAD.dual_level():
            frag = rasterize(fwAD.make_dual(verts, tangent), faces, cam, backend=b)
            out[b] = [fwAD.unpack_dual(x).tangent for x in (frag.zbuf, frag.bary)] + [frag.pix_to_face]
    torch_out, other = out[Backend.TORCH], out[backend]
    assert bool((torch_out[2] >= 0).any()) and torch.equal(other[2], torch_out[2])
    for got, want in zip(other[:2], torch_out[:2]):
        assert want is not None and got is not None
        fg = torch_out[2] >= 0
        torch.testing.assert_close(got[fg], want[fg], rtol=1e-12, atol=1e-12)
