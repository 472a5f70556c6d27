"""Face models: the linear model of paper Eq. 1 (:class:`FaceModel`), CANDIDE-3 and generic mesh loaders.

Every loader returns a :class:`FaceModel` in the head frame and millimetres of :mod:`torchface.conventions`.
"""

from __future__ import annotations

from torchface.model.candide import AnimationSet, WfmFile, WfmUnit, candide3_fapu, load_candide3, parse_wfm
from torchface.model.face_model import (
    FaceModel,
    deform_vertices,
    face_normals,
    interpolate_landmarks,
    vertex_normals,
)
from torchface.model.mesh_loader import load_ict_face_model, load_mesh_model
from torchface.model.model_file import face_model_digest, load_face_model, save_face_model

__all__ = [
    "AnimationSet",
    "FaceModel",
    "WfmFile",
    "WfmUnit",
    "candide3_fapu",
    "deform_vertices",
    "face_model_digest",
    "face_normals",
    "interpolate_landmarks",
    "load_candide3",
    "load_face_model",
    "load_ict_face_model",
    "load_mesh_model",
    "parse_wfm",
    "save_face_model",
    "vertex_normals",
]
