"""A device this machine lacks, wherever torchface first takes one (``load_candide3(device=...)``, ``load_mesh_model``,
``FaceModel.to``, ``FaceTracker.to`` / ``.cuda``, ``NormalisedFace.to`` / ``.cuda``, the ``.to`` of ``LandmarkFit``,
``NormalisedFaceLayout``, ``TexturedMesh``, ``LightState``): one ``ValueError`` naming the
device and the devices here. Before, torch's own error came from deep inside: an ``AssertionError`` "Torch not
compiled with CUDA enabled" for ``"cuda"``, a list of every backend torch knows for a typo, and "Tensor.item() cannot
be called on meta tensors" from the model's checks for ``"meta"``."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchface._device import available_devices, check_device, check_to_device
from torchface.model import FaceModel, load_candide3, load_mesh_model
from torchface.normalise import NormalisedFace, build_normalised_layout
from torchface.rendering import LightState, TexturedMesh
from torchface.tracker import FaceTracker, LandmarkFit, TrackerConfig

NO_CUDA = not torch.cuda.is_available()
NO_MPS = not torch.backends.mps.is_available()


def _mesh_model(device: str) -> FaceModel:
    import trimesh

    tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 2, 1]], process=False)
    return load_mesh_model(tri, blendshapes=np.ones((1, 3, 3)), scale_to_mm=100.0, device=device)


_TAKERS = {
    "load_candide3": lambda d: load_candide3(device=d),
    "load_mesh_model": _mesh_model,
    "FaceModel.to": lambda d: load_candide3().to(d),
    "FaceModel.to(device=)": lambda d: load_candide3().to(device=d, dtype=torch.float64),
    "FaceTracker.to": lambda d: FaceTracker(TrackerConfig(), refine_first=None).to(d),
    "FaceTracker.to(device=, dtype=)": lambda d: FaceTracker(refine_first=None).to(device=d, dtype=torch.float64),
    "NormalisedFace.to": lambda d: NormalisedFace(load_candide3(), size=32).to(d),
    # (the lower-level .to of the results and pieces: torch's own error before)
    "LandmarkFit.to": lambda d: LandmarkFit(*(torch.zeros(1, *s) for s in ((3, 3), (3,), (3,), (2,), (2,), ())),
                                            torch.zeros(1, dtype=torch.int64)).to(d),
    "NormalisedFaceLayout.to": lambda d: build_normalised_layout(load_candide3(), 16, 0.1).to(d),
    "TexturedMesh.to": lambda d: TexturedMesh(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), torch.zeros(3, 2),
                                              torch.ones(3, 4, 4)).to(d, torch.float64),
    "LightState.to(device=)": lambda d: LightState.ambient_only(torch.ones(2)).to(device=d),
}


@pytest.mark.parametrize("taker", sorted(_TAKERS))
@pytest.mark.parametrize(
    "device, message",
    [
        pytest.param("cuda", r"^device 'cuda' is not available: this torch build sees no CUDA GPU",
                     marks=pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")),
        pytest.param("cuda:7", r"^device 'cuda:7' is not available: ",
                     marks=pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")),
        pytest.param("mps", r"^device 'mps' is not available here",
                     marks=pytest.mark.skipif(not NO_MPS, reason="this machine has MPS")),
        ("gpu0", r"^unknown torch device 'gpu0' \(expected e\.g\. cpu, cuda, cuda:1, mps\)"),
        ("meta", r"^device 'meta' holds no data"),
    ],
)  # fmt: skip
def test_a_device_this_machine_lacks_is_one_value_error_naming_it_and_those_it_has(taker, device, message):
    with pytest.raises(ValueError, match=message) as caught:
        _TAKERS[taker](device)
    assert str(caught.value).endswith(f"devices here: {', '.join(available_devices())}")


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
@pytest.mark.parametrize("module", ["FaceTracker", "NormalisedFace"])
@pytest.mark.parametrize("index", [None, 0, torch.device("cuda", 1)])
def test_cuda_without_a_gpu_is_the_same_value_error(module, index):
    made = FaceTracker(refine_first=None) if module == "FaceTracker" else NormalisedFace(load_candide3(), size=32)
    with pytest.raises(ValueError, match=r"^device 'cuda(:\d)?' is not available: .*devices here: cpu"):
        made.cuda(index)


def _accelerator(monkeypatch, current: torch.device | None) -> None:
    """Simulate ``torch.accelerator.current_accelerator()`` giving ``current`` (``torch.accelerator`` came with torch
    2.6: on an older torch the attribute is added for the test, and torchface's reading of it is what is tested)."""
    stand_in = SimpleNamespace(current_accelerator=lambda check_available=False: current)
    monkeypatch.setattr(torch, "accelerator", stand_in, raising=False)


def test_a_cuda_index_beyond_the_gpus_says_how_many_there_are(monkeypatch):
    """``cuda:7`` on a machine of two GPUs (simulated: this check runs on machines without one)."""
    monkeypatch.setattr(torch.backends.cuda, "is_built", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    _accelerator(monkeypatch, torch.device("cuda"))
    with pytest.raises(ValueError, match=r"^device 'cuda:7' is not available: 2 CUDA device\(s\) here \(cuda:0 to "
                                         r"cuda:1\); devices here: cpu, cuda:0, cuda:1"):  # fmt: skip
        check_device("cuda:7")
    assert check_device(torch.device("cuda", 1)) == torch.device("cuda", 1)
    assert check_device(1) == torch.device("cuda", 1)


def test_devices_that_are_here_and_calls_without_a_device_pass():
    assert check_device(None) is None
    assert check_device("cpu") == torch.device("cpu")
    tracker = FaceTracker(refine_first=None).to("cpu").to(torch.float64)
    assert tracker.model.dtype == torch.float64 and tracker.model.device.type == "cpu"
    assert load_candide3(device=torch.device("cpu")).device.type == "cpu"
    with pytest.raises(TypeError, match="device must be a torch.device, a str or an int, got float 1.5"):
        check_device(1.5)  # type: ignore[arg-type]


def test_an_int_is_the_current_accelerators_index(monkeypatch):
    """``.to(0)`` / ``torch.device(0)`` is index 0 of the current accelerator (torch's reading): on Apple silicon
    ``mps:0`` (simulated), refused before as "device 'cuda:0' is not available"; without an accelerator one
    ValueError saying what an int names (simulated: on a GPU machine ``0`` is ``cuda:0``, checked first)."""
    if torch.cuda.is_available():
        assert check_device(0) == torch.device("cuda", 0)
    with monkeypatch.context() as none_here:
        _accelerator(none_here, None)
        none_here.setattr(torch.cuda, "is_available", lambda: False)
        none_here.setattr(torch.backends.mps, "is_available", lambda: False)
        with pytest.raises(ValueError, match=r"^device 0 is not available: an int is an accelerator's \(a GPU's\) "
                                             r"index, and this machine has none; devices here: cpu"):  # fmt: skip
            check_device(0)
    _accelerator(monkeypatch, torch.device("mps"))
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert check_device(0) == torch.device("mps", 0)
    check_to_device(0, torch.float32)  # (FaceTracker.to(0, torch.float32)'s check)


def test_device_checked_module_is_a_base_for_ones_own_modules_typed_as_their_class():
    """``torchface.extending.DeviceCheckedModule``, the base of FaceTracker, NormalisedFace and NormalisedFaceLayer, as
    a package's own module uses it: ``.to`` / ``.cuda`` refuse a device this machine lacks with the one ValueError,
    move it otherwise and return it, typed as the caller's class (they were typed ``Any``: mypy revealed ``Any`` for
    ``NormalisedFace(model).to("cpu")``, ``NormalisedFace`` before)."""
    import typing

    from torchface.extending import DeviceCheckedModule

    class Mine(DeviceCheckedModule):
        def __init__(self) -> None:
            super().__init__()
            self.weight = torch.nn.Parameter(torch.ones(2))

    mine = Mine()
    with pytest.raises(ValueError, match=r"^unknown torch device 'gpu0' .*devices here: "):
        mine.to("gpu0")
    if NO_CUDA:
        with pytest.raises(ValueError, match=r"^device 'cuda' is not available: .*devices here: cpu"):
            mine.cuda()
    assert mine.to(torch.float64) is mine and mine.weight.dtype == torch.float64
    for method in (DeviceCheckedModule.to, DeviceCheckedModule.cuda):
        hints = typing.get_type_hints(method)
        assert isinstance(hints["return"], typing.TypeVar) and hints["return"] is hints["self"], method.__name__
