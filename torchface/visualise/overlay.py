"""Overlay frames: the tracked mesh as a wireframe, the head axes and the confidence (OpenCV drawing).

Geometry is computed batched in torch (:func:`overlay_geometry`: the mesh and the head axes of one pose;
:func:`axes_geometry`: the axes alone, which ``torchface track`` draws at the CSV row's pose while the mesh may be
placed by another after a re-anchoring); drawing is per image at the I/O boundary (:func:`draw_overlay`), on uint8
BGR arrays as OpenCV stores them.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from torch import Tensor

from torchface.conventions import NEAR_PLANE_MM
from torchface.geometry._checks import check_batches, check_bool
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import project_points
from torchface.geometry.transforms import _check_pose, transform_points
from torchface.model.face_model import FaceModel

__all__ = ["AXIS_LENGTH_MM", "axes_geometry", "mesh_edges", "overlay_geometry", "draw_overlay"]

#: Length of the drawn head axes in millimetres.
AXIS_LENGTH_MM: float = 50.0


def mesh_edges(faces: Tensor) -> np.ndarray:
    """``(F, 3)`` triangles -> ``(E, 2)`` int64 unique undirected edges (sorted vertex pairs)."""
    if not isinstance(faces, Tensor) or faces.is_floating_point() or faces.is_complex():  # (a numpy array was told
        # "must be an (F, 3) tensor, got (F, 3)"; float indices were truncated)
        got = f"dtype {faces.dtype}" if isinstance(faces, Tensor) else type(faces).__name__
        raise TypeError(f"faces must be an integer torch.Tensor (F, 3), got {got}")
    if faces.dim() != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be an (F, 3) tensor, got {tuple(faces.shape)}")
    f = faces.detach().cpu().long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], dim=0).sort(dim=1).values
    return torch.unique(e, dim=0).numpy()


def overlay_geometry(
    model: FaceModel, shape_coeffs: Tensor, anim_coeffs: Tensor, rotation: Tensor, translation: Tensor,
    intrinsics: Intrinsics,
) -> tuple[Tensor, Tensor]:
    """Project the posed mesh and the head axes.

    Args:
        model: the face model.
        shape_coeffs: ``(B, S)``; anim_coeffs: ``(B, A)``.
        rotation: ``(B, 3, 3)`` head -> camera; translation: ``(B, 3)`` mm.
        intrinsics: the camera.

    Raises:
        ValueError: a pose of another shape, or batch sizes that do not match (as
            :func:`~torchface.geometry.transform_points`, which poses the mesh; float32 against float64 is promoted).

    Returns:
        ``verts_px (B, V, 2)`` and ``axes_px (B, 4, 2)`` (head origin, then the ends of its +x, +y, +z axes of
        :data:`AXIS_LENGTH_MM`), pixels; points behind the camera (nearer than
        :data:`~torchface.conventions.NEAR_PLANE_MM`) are NaN, which :func:`draw_overlay` does not draw (their
        clamped projection landed anywhere, the image's centre for a point on the optical axis).
    """
    _check_pose(rotation, translation, "rotation", "translation")
    verts = model.deform(shape_coeffs, anim_coeffs)  # (B, V, 3)
    check_batches(("rotation", rotation.shape[0]), ("translation", translation.shape[0]),
                  ("shape_coeffs", verts.shape[0]))  # fmt: skip
    # (transform_points' arithmetic, and its checks: a float64 pose of a float32 model was "expected scalar type Double
    # but found Float", an unbatched rotation an IndexError, a (3,) translation a broadcast error)
    verts_cam = transform_points(rotation, translation, verts)
    return _project_in_front(verts_cam, intrinsics), axes_geometry(rotation, translation, intrinsics)


def axes_geometry(rotation: Tensor, translation: Tensor, intrinsics: Intrinsics) -> Tensor:
    """Project the head axes of a pose: ``(B, 4, 2)`` pixels, the origin ``t`` and the ends ``t + L R e_k`` of its
    +x, +y, +z axes (``L`` = :data:`AXIS_LENGTH_MM`); points nearer than
    :data:`~torchface.conventions.NEAR_PLANE_MM` are NaN (:func:`overlay_geometry`).

    Args:
        rotation: ``(B, 3, 3)`` head -> camera; translation: ``(B, 3)`` mm; intrinsics: the camera.

    Example:
        >>> cam = Intrinsics.default(640, 480)  # f = 640, centre (319.5, 239.5)
        >>> axes_geometry(torch.eye(3)[None], torch.tensor([[0.0, 0.0, 640.0]]), cam)[0]  # +x: image right
        tensor([[319.5000, 239.5000],
                [369.5000, 239.5000],
                [319.5000, 289.5000],
                [319.5000, 239.5000]])
    """
    _check_pose(rotation, translation, "rotation", "translation")  # (a numpy array: "to() received an invalid
    # combination of arguments", an unbatched rotation an IndexError)
    axes = torch.cat([torch.zeros(1, 3), torch.eye(3) * AXIS_LENGTH_MM]).to(rotation)  # (4, 3)
    axes_cam = transform_points(rotation, translation, axes)
    return _project_in_front(axes_cam, intrinsics)


def _project_in_front(points_cam: Tensor, intrinsics: Intrinsics) -> Tensor:
    """``(B, N, 3)`` camera-frame points -> ``(B, N, 2)`` pixels, NaN for those nearer than the near plane."""
    px = project_points(points_cam, intrinsics)
    return torch.where((points_cam[..., 2:] > NEAR_PLANE_MM), px, torch.full_like(px, float("nan")))


def _pt(p: np.ndarray, limit: float) -> tuple[int, int]:
    q = np.clip(np.asarray(p, dtype=np.float64), -limit, limit)
    return int(round(float(q[0]))), int(round(float(q[1])))


def draw_overlay(
    image_bgr: np.ndarray, verts_px: np.ndarray, edges: np.ndarray, axes_px: np.ndarray, confidence: float,
    success: bool, label: str = "", confidence_label: str = "conf", unusable_label: str = "LOST",
) -> np.ndarray:
    """Draw one overlay frame (returns a new uint8 BGR image).

    Args:
        image_bgr: ``(H, W, 3)`` uint8 BGR frame.
        verts_px: ``(V, 2)`` projected vertices; edges: ``(E, 2)`` vertex pairs (:func:`mesh_edges`); an edge
            with a non-finite end (a vertex behind the camera, :func:`overlay_geometry`) is not drawn.
        axes_px: ``(4, 2)`` head origin and axis ends (:func:`overlay_geometry`, :func:`axes_geometry`); x red,
            y green, z blue (an axis with a non-finite end is not drawn).
        confidence: the frame's confidence in ``[0, 1]`` (``TrackResult.confidence``: with template management
            the dissimilarity confidence).
        success: whether the frame's estimate is usable (a failed or lost frame draws the mesh grey).
        label: text drawn before the confidence (e.g. the frame number).
        confidence_label: what the confidence is ("dissim. conf": the dissimilarity confidence; "conf" for the
            residual confidence of a tracker without template management).
        unusable_label: the word drawn after the confidence when ``success`` is False: ``"LOST"`` (status 3) or
            ``"FAILED"`` (status 2: no usable estimate this frame, the previous one drawn).

    Raises:
        TypeError: ``image_bgr`` is not a numpy array (a tensor: ``.cpu().numpy()``), or ``success`` is not a bool
            (or a one-element bool tensor).
        ValueError: ``image_bgr`` is not ``(H, W, 3)`` uint8, or ``edges`` are not ``(E, 2)`` integer indices of
            ``verts_px``' vertices, or ``verts_px`` / ``axes_px`` are not one frame's
            ``(V, 2)`` / ``(4, 2)`` (:func:`overlay_geometry`'s batched ``(B, V, 2)``: take ``[b]``), or
            ``confidence`` is not one number (a one-element tensor or array is taken as its number).
    """
    if not isinstance(image_bgr, np.ndarray):  # (a tensor was told "must be (H, W, 3) uint8, got (H, W, 3) uint8")
        hint = " (a tensor: .cpu().numpy() of an (H, W, 3) uint8 BGR image)" if isinstance(image_bgr, Tensor) else ""
        raise TypeError(f"image_bgr must be a numpy array (H, W, 3) uint8, got {type(image_bgr).__name__}{hint}")
    if image_bgr.ndim != 3 or image_bgr.shape[2] != 3 or image_bgr.dtype != np.uint8:
        raise ValueError(f"image_bgr must be (H, W, 3) uint8, got {image_bgr.shape} {image_bgr.dtype}")
    # (a tensor that requires grad, as overlay_geometry's of one: "Can't call numpy() on Tensor that requires grad")
    v, a, e = (np.asarray(x.detach().cpu() if isinstance(x, Tensor) else x) for x in (verts_px, axes_px, edges))
    v, a = v.astype(np.float64, copy=False), a.astype(np.float64, copy=False)
    # (overlay_geometry's batched (B, V, 2) and (B, 4, 2) given as they come: "IndexError: index 1 is out of bounds
    # for axis 0 with size 1", or, with B > 1, the edges drawn between the streams' vertices)
    for name, x, n in (("verts_px", v, "V"), ("axes_px", a, "4")):
        if x.ndim != 2 or x.shape[1] != 2 or (n == "4" and x.shape[0] != 4):
            one = " (one frame's: overlay_geometry's gives (B, ...), take [b])" if x.ndim == 3 else ""
            raise ValueError(f"{name} must be ({n}, 2) pixels, got shape {x.shape}{one}")
    if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):  # (numpy's IndexError "arrays used
        # as indices must be of integer type")
        raise ValueError(f"edges must be (E, 2) integer vertex pairs (mesh_edges), got shape {e.shape} {e.dtype}")
    if e.size and (int(e.min()) < 0 or int(e.max()) >= v.shape[0]):  # (an IndexError, or a negative one wrapped)
        raise ValueError(f"edges must index the {v.shape[0]} vertices of verts_px, got indices in "
                         f"[{int(e.min())}, {int(e.max())}]")  # fmt: skip
    if isinstance(success, Tensor) and success.dtype == torch.bool and success.numel() == 1:
        success = bool(success)  # (TrackResult.success[b], as confidence's one-element tensor is its number)
    success = check_bool(success, "success")  # ("no" drew the mesh green)
    try:  # (a one-element tensor, TrackResult.confidence[b:b + 1], met Tensor.__format__'s TypeError at ".2f")
        confidence = float(confidence)
    except (TypeError, ValueError, RuntimeError):
        shape = getattr(confidence, "shape", None)
        raise ValueError(f"confidence must be one frame's number, got {type(confidence).__name__}"
                         + (f" of shape {tuple(shape)} (a batch's: take [b])" if shape is not None else "")) from None
    out = image_bgr.copy()
    H, W = out.shape[:2]
    limit = 4.0 * max(H, W)
    ends = v[e]  # (E, 2, 2)
    # (a non-finite end used to become a corner far off the image, and its edge a line across it)
    lines = np.round(np.clip(ends[np.isfinite(ends).all(axis=(1, 2))], -limit, limit)).astype(np.int32)
    colour = (80, 255, 80) if success else (160, 160, 160)
    if len(lines):
        cv2.polylines(out, list(lines), isClosed=False, color=colour, thickness=1, lineType=cv2.LINE_AA)
    for k, c in zip(range(1, 4), ((0, 0, 255), (0, 255, 0), (255, 0, 0))):
        if np.isfinite(a[0]).all() and np.isfinite(a[k]).all():
            cv2.line(out, _pt(a[0], limit), _pt(a[k], limit), c, 2, cv2.LINE_AA)
    scale = max(0.35, min(W, H) / 600.0)
    text = f"{label} {confidence_label} {confidence:.2f}" + ("" if success else f" {unusable_label}")
    bar = int(round(max(0.0, min(1.0, confidence)) * (W // 4))) if math.isfinite(confidence) else 0  # NaN: none
    # (rectangles include both corners: the track is W // 4 pixels wide and the bar `bar`; a confidence of 0 or NaN
    # drew a 1-pixel bar, and every bar was one pixel longer than its share)
    cv2.rectangle(out, (4, H - 10), (4 + W // 4 - 1, H - 4), (60, 60, 60), -1)
    if bar > 0:
        cv2.rectangle(out, (4, H - 10), (4 + bar - 1, H - 4), (0, 200, 255) if success else (0, 0, 255), -1)
    (tw, th), base = cv2.getTextSize(text.strip(), cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(out, (2, H - 16 - th - 3), (8 + tw, H - 16 + base), (0, 0, 0), -1)
    cv2.putText(out, text.strip(), (4, H - 16), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out
