"""Renderable subjects: a linear textured face (CANDIDE-3 textured from a frontal photograph) or a scan.

A :class:`Subject` is everything the sequence renderer needs: linear geometry
``g = mean + S sigma + A alpha`` (paper Eq. 1; a rigid scan has ``S = A = 0``), triangles, per-vertex
texture coordinates and texture, and the 68 iBUG landmarks as fixed barycentric combinations of
vertices (so they move with the surface) together with the triangle each landmark lies on.

Texturing CANDIDE-3 from a frontal photograph (:func:`candide_subject`):

1. the photograph and its 68 landmarks: by default a frontal, evenly lit render of the James scan
   (:func:`james_frontal_photo`), whose landmarks are known exactly by projecting the scan's;
   alternatively the packaged astronaut portrait with hand-marked landmarks;
2. CANDIDE-3's pose and shape coefficients are fitted to those landmarks (paper Eq. 2,
   :func:`fit_landmarks`);
3. each vertex's texture coordinate is the projection of the fitted vertex into the photograph.

The fitted shape coefficients are the subject's identity ("a person"), so that the texture sits on
the geometry it was mapped with.
"""

from __future__ import annotations

import csv
import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.so3 import axis_angle_to_matrix
from torchface.geometry.transforms import transform_points
from torchface.rendering.shading import LightState, render
from torchface.rendering.visibility import vertex_normals
from torchface.synth.james import load_james

__all__ = [
    "Subject",
    "Photo",
    "LandmarkFit",
    "james_subject",
    "candide_subject",
    "james_frontal_photo",
    "astronaut_photo",
    "fit_landmarks",
    "candide_photo_mapping",
    "build_candide_textures",
    "SUBJECTS",
    "PHOTOS",
    "get_subject",
]

#: Subject names accepted by :func:`get_subject`.
SUBJECTS: tuple[str, ...] = ("candide3", "james")
#: Photographs CANDIDE-3 can be textured from.
PHOTOS: tuple[str, ...] = ("james", "astronaut")


@dataclass(frozen=True, eq=False)
class Subject:
    """A textured linear face or scan in the head frame (millimetres, see :mod:`torchface.conventions`).

    Attributes:
        name: ``"candide3"`` or ``"james"``.
        mean: ``(V, 3)`` neutral vertices.
        shape_units: ``(S, V, 3)`` shape basis (``S = 0`` for a scan).
        animation_units: ``(A, V, 3)`` animation basis (``A = 0`` for a scan).
        animation_names: ``A`` names.
        animation_ranges: ``(A, 2)`` plausible ranges.
        shape_coeffs: ``(S,)`` the person's shape coefficients (used when a sequence gives none).
        faces: ``(F, 3)`` int64 triangles, outward.
        uv: ``(V, 2)`` texture coordinates (``(0, 0)`` = texture top-left).
        texture: ``(3, Ht, Wt)`` RGB albedo in ``[0, 1]``.
        weld: ``(V,)`` int64; vertices with the same weld index share one normal (texture seams).
        landmark_vertices: ``(K, 3)`` int64, landmark ``k = sum_j w[k, j] verts[idx[k, j]]``.
        landmark_weights: ``(K, 3)`` weights (rows sum to 1).
        landmark_faces: ``(K,)`` int64 triangle each landmark lies on (for visibility tests).
    """

    name: str
    mean: Tensor
    shape_units: Tensor
    animation_units: Tensor
    animation_names: tuple[str, ...]
    animation_ranges: Tensor
    shape_coeffs: Tensor
    faces: Tensor
    uv: Tensor
    texture: Tensor
    weld: Tensor
    landmark_vertices: Tensor
    landmark_weights: Tensor
    landmark_faces: Tensor

    @property
    def num_shape(self) -> int:
        """``S``."""
        return int(self.shape_units.shape[0])

    @property
    def num_animation(self) -> int:
        """``A``."""
        return int(self.animation_units.shape[0])

    def deform(self, shape_coeffs: Tensor | None, anim_coeffs: Tensor | None, batch: int) -> Tensor:
        """``(B, S)`` and ``(B, A)`` coefficients (``None`` = zeros) -> ``(B, V, 3)`` vertices (Eq. 1).

        Computed in the coefficients' dtype (the model's when both are ``None``).
        """
        given = [c for c in (shape_coeffs, anim_coeffs) if c is not None]
        dt = given[0].dtype if given else self.mean.dtype
        verts = self.mean.to(dt).unsqueeze(0).expand(batch, -1, -1)
        if shape_coeffs is not None and self.num_shape:
            verts = verts + torch.einsum("bs,svc->bvc", shape_coeffs.to(dt), self.shape_units.to(dt))
        if anim_coeffs is not None and self.num_animation:
            verts = verts + torch.einsum("ba,avc->bvc", anim_coeffs.to(dt), self.animation_units.to(dt))
        return verts.contiguous()

    def vertex_normals(self, verts: Tensor) -> Tensor:
        """``(B, V, 3)`` -> ``(B, V, 3)`` unit normals, shared across welded seam duplicates."""
        b = verts.shape[0]
        n_weld = int(self.weld.max()) + 1
        # Any representative position per welded vertex works: duplicates coincide.
        rep = torch.zeros(n_weld, dtype=torch.int64).scatter_(0, self.weld, torch.arange(self.weld.shape[0]))
        welded = verts[:, rep]
        normals = vertex_normals(welded, self.weld[self.faces])
        return normals[:, self.weld].reshape(b, -1, 3)

    def landmarks_3d(self, verts: Tensor) -> Tensor:
        """``(B, V, 3)`` -> ``(B, K, 3)`` landmark positions."""
        corners = verts[:, self.landmark_vertices]  # (B, K, 3, 3)
        return (self.landmark_weights.to(verts.dtype).unsqueeze(-1) * corners).sum(dim=-2)


@dataclass(frozen=True, eq=False)
class Photo:
    """A frontal photograph with landmarks.

    Attributes:
        name: photo name.
        image: ``(3, H, W)`` RGB in ``[0, 1]``.
        landmarks_px: ``(K, 2)`` pixel positions (iBUG-68 indices ``landmark_ids``).
        landmark_ids: ``(K,)`` int64 iBUG-68 index of each landmark.
        intrinsics: camera of the photograph (a guess for real photographs).
    """

    name: str
    image: Tensor
    landmarks_px: Tensor
    landmark_ids: Tensor
    intrinsics: Intrinsics


@dataclass(frozen=True, eq=False)
class LandmarkFit:
    """Result of :func:`fit_landmarks`.

    Attributes:
        rotation: ``(3, 3)`` head-to-camera rotation.
        translation: ``(3,)`` millimetres.
        shape_coeffs: ``(S,)`` fitted shape coefficients.
        rms_px: root-mean-square landmark reprojection error in pixels.
    """

    rotation: Tensor
    translation: Tensor
    shape_coeffs: Tensor
    rms_px: float


def _data_path(*parts: str) -> Path:
    return Path(str(resources.files("torchface").joinpath("data", *parts)))


def _faces_of_landmarks(faces: Tensor, landmark_vertices: Tensor, landmark_weights: Tensor) -> Tensor:
    """For each landmark, a triangle containing every vertex it has a non-zero weight on."""
    out = []
    face_sets = faces.tolist()
    for idx, w in zip(landmark_vertices.tolist(), landmark_weights.tolist()):
        need = {i for i, wi in zip(idx, w) if abs(wi) > 0}
        match = [k for k, f in enumerate(face_sets) if need.issubset(f)]
        if not match:
            raise ValueError(f"no triangle contains landmark vertices {sorted(need)}")
        out.append(match[0])
    return torch.tensor(out, dtype=torch.int64)


@functools.lru_cache(maxsize=2)
def james_subject() -> Subject:
    """The James scan as a rigid subject (``S = A = 0``), landmarks on its surface."""
    scan = load_james()
    v = scan.verts.shape[0]
    return Subject(
        name="james",
        mean=scan.verts,
        shape_units=scan.verts.new_zeros(0, v, 3),
        animation_units=scan.verts.new_zeros(0, v, 3),
        animation_names=(),
        animation_ranges=scan.verts.new_zeros(0, 2),
        shape_coeffs=scan.verts.new_zeros(0),
        faces=scan.faces,
        uv=scan.uv,
        texture=scan.texture,
        weld=scan.weld,
        landmark_vertices=scan.faces[scan.landmark_faces],
        landmark_weights=scan.landmark_bary,
        landmark_faces=scan.landmark_faces,
    )


@functools.lru_cache(maxsize=2)
def james_frontal_photo(size: int = 512) -> Photo:
    """A frontal, evenly lit (ambient only) render of James on mid-grey, with its exact 68 landmarks.

    The camera is far (1 m) with a long focal length so the photograph is close to orthographic.
    """
    subject = james_subject()
    cam = Intrinsics(size, size, 3.0 * size, 3.0 * size, (size - 1) / 2.0, (size - 1) / 2.0)
    t = torch.tensor([[0.0, 10.0, 1000.0]])
    verts = subject.mean.unsqueeze(0) + t.unsqueeze(1)
    normals = subject.vertex_normals(verts)
    bg = torch.full((1, 3, size, size), 0.5)
    image, _, _ = render(
        verts, subject.faces, subject.uv, subject.texture, normals, LightState.ambient_only(torch.ones(1)), cam, bg
    )
    lm = project_points(subject.landmarks_3d(verts), cam)[0]
    return Photo("james", image[0], lm, torch.arange(68), cam)


@functools.lru_cache(maxsize=1)
def astronaut_photo() -> Photo:
    """The astronaut portrait (public domain, NASA) crop with hand-marked landmarks (``astronaut_landmarks.csv``)."""
    import cv2

    img_path = _data_path("photos", "astronaut_face.png")
    csv_path = _data_path("photos", "astronaut_landmarks.csv")
    bgr = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FileNotFoundError(f"packaged photo missing: {img_path}")
    image = _image_to_tensor(bgr)
    ids, pts = [], []
    with open(csv_path, newline="") as fh:
        for row in csv.DictReader(line for line in fh if not line.startswith("#")):
            ids.append(int(row["ibug_index"]))
            pts.append((float(row["x"]), float(row["y"])))
    h, w = image.shape[1:]
    # A portrait lens: focal length about 3x the image width (close to orthographic, like the render).
    cam = Intrinsics(w, h, 3.0 * w, 3.0 * w, (w - 1) / 2.0, (h - 1) / 2.0)
    return Photo("astronaut", image, torch.tensor(pts), torch.tensor(ids, dtype=torch.int64), cam)


def fit_landmarks(
    model_mean: Tensor,
    shape_units: Tensor,
    landmarks_fn,
    landmarks_px: Tensor,
    landmark_ids: Tensor,
    intrinsics: Intrinsics,
    weights: Tensor | None = None,
    shape_prior: float = 1.0,
    iterations: int = 100,
) -> LandmarkFit:
    """Fit pose and shape coefficients to 2D landmarks (paper Eq. 2) with L-BFGS in float64.

    Minimises ``sum_k w_k |pi(R (g_bar + S sigma)_k + t) - p_k|^2 + shape_prior * |sigma|^2``
    over the axis-angle of ``R``, ``t`` and ``sigma`` (``|.|`` in pixels, the prior keeps the
    coefficients near the mean where landmarks do not constrain them).

    Args:
        model_mean: ``(V, 3)`` mean shape ``g_bar``.
        shape_units: ``(S, V, 3)`` shape basis.
        landmarks_fn: maps ``(B, V, 3)`` vertices to ``(B, 68, 3)`` landmarks.
        landmarks_px: ``(K, 2)`` observed pixel positions.
        landmark_ids: ``(K,)`` iBUG-68 index of each observation.
        intrinsics: camera of the photograph.
        weights: ``(K,)`` confidences ``w_k`` (ones when ``None``).
        shape_prior: weight of the ridge prior on ``sigma``.
        iterations: L-BFGS iterations.

    Returns:
        :class:`LandmarkFit`.
    """
    dt = torch.float64
    mean, units = model_mean.to(dt), shape_units.to(dt)
    obs = landmarks_px.to(dt)
    w = torch.ones(obs.shape[0], dtype=dt) if weights is None else weights.to(dt)
    # Initial depth from the spread of the landmarks against the model's.
    lm0 = landmarks_fn(mean.unsqueeze(0))[0, landmark_ids]
    spread_model = (lm0[:, :2] - lm0[:, :2].mean(0)).norm(dim=-1).mean()
    spread_px = (obs - obs.mean(0)).norm(dim=-1).mean()
    z0 = float(intrinsics.fx * spread_model / spread_px)
    c = obs.mean(0)
    t0 = torch.tensor([(c[0] - intrinsics.cx) * z0 / intrinsics.fx, (c[1] - intrinsics.cy) * z0 / intrinsics.fy, z0], dtype=dt)
    aa = torch.zeros(1, 3, dtype=dt, requires_grad=True)
    t = t0.clone().unsqueeze(0).requires_grad_(True)
    sigma = torch.zeros(1, units.shape[0], dtype=dt, requires_grad=True)
    opt = torch.optim.LBFGS([aa, t, sigma], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

    def residual() -> Tensor:
        verts = mean.unsqueeze(0) + torch.einsum("bs,svc->bvc", sigma, units)
        lm = landmarks_fn(verts)[:, landmark_ids]
        px = project_points(transform_points(axis_angle_to_matrix(aa), t, lm), intrinsics)
        return (px[0] - obs) * w.sqrt().unsqueeze(-1)

    def closure() -> Tensor:
        opt.zero_grad()
        loss = (residual() ** 2).sum() + shape_prior * (sigma**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        r = residual()
        rms = float((r**2).sum(-1).div(w.clamp(min=1e-12)).mean().sqrt())
    return LandmarkFit(axis_angle_to_matrix(aa.detach())[0], t.detach()[0], sigma.detach()[0], rms)


def _image_to_tensor(bgr: np.ndarray) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1).float().div(255.0).contiguous()


def _fit_weights(landmark_ids: Tensor) -> Tensor:
    # Jaw contour points are less reliable correspondences on CANDIDE's coarse outline.
    return torch.where(landmark_ids < 17, 0.3, 1.0).to(torch.float64)


def candide_photo_mapping(photo: Photo) -> tuple[Tensor, Tensor, float]:
    """Fit CANDIDE-3 to a photograph's landmarks and map its vertices into it.

    Returns:
        ``uv (V, 2)`` texture coordinates of every vertex in the photograph, the fitted
        ``shape_coeffs (S,)`` and the fit's landmark RMS error in pixels.
    """
    from torchface.model import load_candide3

    model = load_candide3(dtype=torch.float64)
    fit = fit_landmarks(
        model.mean, model.shape_units, model.landmarks_3d, photo.landmarks_px, photo.landmark_ids,
        photo.intrinsics, weights=_fit_weights(photo.landmark_ids),
        shape_prior=50.0 if photo.landmark_ids.numel() == 68 else 200.0,
    )
    verts = model.mean + torch.einsum("s,svc->vc", fit.shape_coeffs, model.shape_units)
    px = project_points(transform_points(fit.rotation[None], fit.translation[None], verts[None]), photo.intrinsics)[0]
    h, w = photo.image.shape[1:]
    uv = torch.stack([(px[:, 0] + 0.5) / w, (px[:, 1] + 0.5) / h], dim=-1).clamp(0.0, 1.0)
    return uv, fit.shape_coeffs, fit.rms_px


def build_candide_textures(out_dir: str | Path) -> dict[str, float]:
    """Precompute CANDIDE-3's texture mapping for every photo in :data:`PHOTOS` (development-time tool).

    Writes ``james_render.jpg`` (the frontal James render used as a photograph) and, per photo,
    ``candide3_uv_<photo>.npz`` with ``uv (V, 2)``, ``shape_coeffs (S,)``, the photo's landmarks
    and the fit's RMS error.

    Returns:
        The fit RMS error (pixels) per photo.
    """
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = {}
    for name in PHOTOS:
        if name == "james":
            photo = james_frontal_photo()
            bgr = (photo.image.permute(1, 2, 0).flip(-1).clamp(0, 1) * 255).round().to(torch.uint8).numpy()
            cv2.imwrite(str(out / "james_render.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, 92])
        else:
            photo = astronaut_photo()
        uv, shape, rms = candide_photo_mapping(photo)
        cam = photo.intrinsics
        np.savez_compressed(
            out / f"candide3_uv_{name}.npz",
            uv=uv.numpy().astype(np.float32),
            shape_coeffs=shape.numpy().astype(np.float32),
            landmarks_px=photo.landmarks_px.numpy().astype(np.float32),
            landmark_ids=photo.landmark_ids.numpy().astype(np.int64),
            intrinsics=np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height], dtype=np.float64),
            rms_px=np.array(rms),
        )
        figures[f"{name}_fit_rms_px"] = rms
    return figures


_PHOTO_FILES: dict[str, str] = {"james": "james_render.jpg", "astronaut": "astronaut_face.png"}


@functools.lru_cache(maxsize=4)
def candide_subject(photo: str = "james") -> Subject:
    """CANDIDE-3 (11 AUVs) textured from a frontal photograph (module docstring for the method).

    The mapping is precomputed by :func:`build_candide_textures` and shipped in ``data/photos``.

    Args:
        photo: ``"james"`` (render of the James scan, exact landmarks) or ``"astronaut"``.

    Returns:
        The subject; its ``shape_coeffs`` are those fitted to the photograph.
    """
    import cv2

    from torchface.model import load_candide3

    if photo not in PHOTOS:
        raise ValueError(f"photo must be one of {PHOTOS}, got {photo!r}")
    model = load_candide3(dtype=torch.float32)
    img_path = _data_path("photos", _PHOTO_FILES[photo])
    map_path = _data_path("photos", f"candide3_uv_{photo}.npz")
    bgr = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
    if bgr is None or not map_path.is_file():
        raise FileNotFoundError(f"packaged photo texture missing: {img_path} / {map_path}")
    with np.load(map_path) as z:
        uv = torch.from_numpy(z["uv"]).float()
        shape = torch.from_numpy(z["shape_coeffs"]).float()
    if uv.shape != (model.num_vertices, 2) or shape.shape != (model.num_shape,):
        raise ValueError(f"{map_path} does not match the CANDIDE-3 model (rebuild with scripts/build_synth_data.py)")
    lm_faces = _faces_of_landmarks(model.faces, model.landmark_vertices, model.landmark_weights)
    return Subject(
        name="candide3",
        mean=model.mean,
        shape_units=model.shape_units,
        animation_units=model.animation_units,
        animation_names=model.animation_names,
        animation_ranges=model.animation_ranges,
        shape_coeffs=shape,
        faces=model.faces,
        uv=uv,
        texture=_image_to_tensor(bgr),
        weld=torch.arange(model.num_vertices),
        landmark_vertices=model.landmark_vertices,
        landmark_weights=model.landmark_weights,
        landmark_faces=lm_faces,
    )


def get_subject(name: str, photo: str = "james") -> Subject:
    """Subject by name: ``"candide3"`` (textured from ``photo``) or ``"james"``."""
    if name == "candide3":
        return candide_subject(photo)
    if name == "james":
        return james_subject()
    raise ValueError(f"subject must be one of {SUBJECTS}, got {name!r}")

