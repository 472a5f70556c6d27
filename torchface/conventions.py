"""The conventions torchface relies on, written down once.

Every module that depends on one of these points here (``see torchface.conventions``).

Shape vocabulary (used in every docstring)
------------------------------------------
``B`` batch (independent streams / samples), ``V`` vertices, ``F`` triangles, ``S`` shape units,
``A`` animation units, ``L`` illumination terms, ``P`` packed parameters, ``N`` template points,
``K`` landmarks, ``T`` frames, ``C`` channels, ``H x W`` image height and width.
Tensors are batch-first; the model's topology and bases are unbatched and broadcast.

Camera frame
------------
OpenCV: ``+x`` right in the image, ``+y`` down in the image, ``+z`` forward (away from the camera,
into the scene). The camera centre is the origin. Points in this frame are named ``*_cam``.

Model (head) frame
------------------
Every face model is converted on load into a head frame aligned with the camera frame when the
face looks straight into the camera: ``+x`` toward the subject's LEFT (image right when frontal),
``+y`` toward the chin (down), ``+z`` toward the back of the head (away from the viewer).
Hence the identity rotation is a frontal face, and a pose is the rigid map
``X_cam = R @ X_model + t`` (``R`` in SO(3), ``t`` in millimetres). CANDIDE-3's own file frame
(+x subject's left, +y up, +z toward the viewer) is a 180 degree rotation about x away from this one,
so loading keeps triangle orientation (outward normals stay outward).

Units
-----
Model coordinates and translations are millimetres. CANDIDE-3 is stored in normalised units; it is
scaled by :data:`MM_PER_CANDIDE_UNIT`, which maps the MPEG-4 eye-separation FAPU of the file (0.613
units, the distance between the pupils) to a typical adult interpupillary distance of 63 mm.
Animation-unit and shape-unit coefficients are dimensionless (the file's own scale).

Rotations
---------
Parameterised as axis-angle vectors ``(B, 3)`` (direction = axis, norm = angle in radians), mapped to
matrices with the exponential map (Rodrigues). For *reporting only*, a rotation is decomposed into
yaw, pitch and roll in degrees with the intrinsic order

    ``R = R_y(yaw) @ R_x(pitch) @ R_z(roll)``

about the camera axes (all right-handed). With the head frame above, from the camera's point of view:
positive yaw turns the nose toward image LEFT (the subject turns to their right), positive pitch tips
the nose DOWN, positive roll rotates the face clockwise in the image. Pitch is kept in [-90, 90].

Images and pixels
-----------------
Images are ``(B, C, H, W)`` float tensors in ``[0, 1]``, RGB channel order (OpenCV's BGR is converted
at the I/O boundary). Pixel ``(u, v)`` (column, row) has its centre at integer coordinates; the image
covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. The rasterizer samples at pixel centres, and bilinear
sampling maps pixel coordinates to ``grid_sample``'s normalised coordinates with
``align_corners=True`` (``x_norm = 2 u / (W - 1) - 1``).

Landmarks are pixels too. Points in normalised image coordinates (``x / W``, ``y / H``, MediaPipe's) are refused
where they cannot be pixels of a trackable face: all within :data:`NORMALISED_LANDMARK_RANGE` along both axes
(a little outside ``[0, 1]`` for a face partly out of the frame), spanning at most
:data:`NORMALISED_LANDMARK_MAX_SPAN`, in frames of at least :data:`NORMALISED_CHECK_MIN_SIDE` pixels a side
(:func:`torchface.tracker.fit.check_pixel_landmarks`, :func:`torchface.io.check_landmarks`); pixels of them:
``x * W``, ``y * H`` (MediaPipe's ``x / W`` is of pixel coordinates with centres at integers, measured:
see :class:`torchface.detect.facemesh.MediaPipeDetector`). One stream's among streams in pixels, or a detector's
for a stream (:func:`torchface.tracker.fit.normalised_streams`), fail that stream alone (``TrackResult.start_failure``).
MediaPipe's face mesh points (:data:`MEDIAPIPE_MESH_POINT_COUNTS` of them) are not the iBUG-68 landmarks that
CANDIDE-3 and the detectors use: a count of theirs where 68 are wanted is refused with :data:`MEDIAPIPE_MESH_HINT`,
and one of another known set's (:data:`OTHER_LANDMARK_SETS`) with :func:`other_landmark_set_hint`.

Projection
----------
Pinhole, no distortion: ``u = fx X / Z + cx``, ``v = fy Y / Z + cy``. By default
``fx = fy = max(W, H)`` (about 53 degrees of horizontal field of view at 4:3) and the principal point is
the image centre ``((W - 1) / 2, (H - 1) / 2)``; see :class:`torchface.geometry.camera.Intrinsics`.
"""

from __future__ import annotations

#: Millimetres per CANDIDE-3 model unit (eye-separation FAPU 0.613 units == 63 mm).
MM_PER_CANDIDE_UNIT: float = 63.0 / 0.613

#: Points closer to the camera than this (millimetres) are treated as behind it.
NEAR_PLANE_MM: float = 1.0

#: Where landmarks in normalised image coordinates lie (module docstring, "Images and pixels"), along each axis.
NORMALISED_LANDMARK_RANGE: tuple[float, float] = (-0.5, 1.5)

#: The most such landmarks span along either axis (a face in pixels spanning no more fails the landmark fit).
NORMALISED_LANDMARK_MAX_SPAN: float = 1.5

#: Frames with a side under this many pixels are not checked for normalised landmarks: a face in pixels there
#: spans about a pixel as well (and fails the fit, as it did before the check).
NORMALISED_CHECK_MIN_SIDE: int = 8

#: iBUG-68's left-right mirror: point ``k`` of a face is point ``IBUG68_MIRROR[k]`` of its mirror image (the jaw's
#: 0-16 reversed, the brows' 17-26, the nose wings' 31-35, the eyes' 36-47 and the lips' 48-67 each with its
#: partner; the nose bridge 27-30 and the midline points on themselves). :func:`torchface.io.mirror_landmarks`.
IBUG68_MIRROR: tuple[int, ...] = (
    *range(16, -1, -1), *range(26, 16, -1), *range(27, 31), *range(35, 30, -1), *range(45, 41, -1),
    *range(47, 45, -1), *range(39, 35, -1), *range(41, 39, -1), *range(54, 47, -1), *range(59, 54, -1),
    *range(64, 59, -1), *range(67, 64, -1),
)  # fmt: skip

#: Point counts of MediaPipe's face mesh (468 points; 478 with the irises' 10, FaceLandmarker's).
MEDIAPIPE_MESH_POINT_COUNTS: tuple[int, ...] = (468, 478)

#: Said where such a count of landmarks arrives where the 68 iBUG points are wanted (it was told the count alone).
MEDIAPIPE_MESH_HINT: str = (
    "MediaPipe's face mesh points? The 68 iBUG / 300-W landmarks are wanted, in their order (as dlib's 68-point "
    "predictor, OpenFace and torchface.detect give them), in pixels; torchface.detect.facemesh.mesh_to_ibug68 maps "
    "MediaPipe's 478 (or 468) points to them"
)

#: Other landmark sets, by their point count, that arrive where the 68 iBUG points are wanted (they were told the
#: count alone, or that a missing point stays as a NaN row): :func:`other_landmark_set_hint`.
OTHER_LANDMARK_SETS: dict[int, str] = {
    5: "a 5-point set's (eyes, nose tip, mouth corners: RetinaFace's, MTCNN's)",
    70: "OpenPose's 70 face points",
    98: "WFLW's 98 points",
    106: "a 106-point set's (InsightFace's 2d106det, JD-landmark's)",
}


def other_landmark_set_hint(count: int, first_68: str) -> str | None:
    """What is said of ``count`` landmarks given where the 68 iBUG points are wanted, where they are another known
    set's (:data:`OTHER_LANDMARK_SETS`; None for other counts): OpenPose's 70 hold the 68 in their order, then the
    two pupils (``first_68``, the caller's code that keeps them: ``"points[:68]"``); the other sets are other
    points, of which those they share may be given at their iBUG index, the others NaN rows (a 5-point set shares
    3, fewer than a start takes).

    Example:
        >>> other_landmark_set_hint(70, "points[:68]")
        "OpenPose's 70 face points? Its first 68 are the iBUG points, in their order (then the pupils): points[:68]"
    """
    what = OTHER_LANDMARK_SETS.get(count)
    if what is None:
        return None
    if count == 70:
        return f"{what}? Its first 68 are the iBUG points, in their order (then the pupils): {first_68}"
    wanted = f"{what}? The 68 iBUG / 300-W landmarks are wanted, in their order (as dlib's 68-point predictor, " \
        "OpenFace and torchface.detect give them)"
    if count == 5:
        return (f"{wanted}: of the 5, the nose tip and the mouth corners alone are iBUG points (30, 48, 54), fewer "
                "than the 4 a start takes")
    return f"{wanted}: another set's points are other points (those it shares may be given at their iBUG index, " \
        "the others as NaN rows)"


def half_precision_rounding(dtype: str, eps: float) -> str:
    """How ``dtype`` (a half-precision type's name; ``eps`` its machine epsilon, the step from 1 to 2) rounds pixel
    coordinates, for the warnings of float16 and bfloat16 landmarks (the Python API's tensors,
    :func:`torchface.tracker.fit.warn_half_precision_landmarks`, and a landmarks file's float16 array,
    :func:`torchface.io.check_landmarks`): a coordinate of ``2**k`` pixels or more is a multiple of ``2**k * eps``.

    Example:
        >>> half_precision_rounding("torch.bfloat16", 2.0**-7)
        'torch.bfloat16, which rounds pixel coordinates to steps of 0.5 px from 64, 1 px from 128 and 2 px from 256'
    """
    return (f"{dtype}, which rounds pixel coordinates to steps of 0.5 px from {0.5 / eps:g}, 1 px from {1 / eps:g} "
            f"and 2 px from {2 / eps:g}")
