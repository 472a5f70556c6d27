"""A package-wide convention: the dataclasses that hold tensors (results, states, model data, specs) compare by
identity (``eq=False``, as :class:`torchface.model.FaceModel`), since a field-wise ``==`` on tensors raised
"Boolean value of Tensor with more than one value is ambiguous"."""

from __future__ import annotations

import dataclasses
import enum
import importlib
import inspect
import math
import pkgutil
import re
import sys

import numpy as np
import pytest
import torch

import torchface
import training_hooks
from torchface.solver.least_squares import SolveResult


def _tensor_dataclasses() -> list[type]:
    """The dataclasses of ``torchface`` and ``training_hooks`` with a tensor field."""
    found = []
    packages = [(torchface.__path__, "torchface."), (training_hooks.__path__, "training_hooks.")]
    for info in (i for path, prefix in packages for i in pkgutil.walk_packages(path, prefix)):
        module = importlib.import_module(info.name)
        for obj in vars(module).values():
            if inspect.isclass(obj) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__:
                if any("Tensor" in str(f.type) for f in dataclasses.fields(obj)):
                    found.append(obj)
    return found


def test_every_dataclass_holding_tensors_compares_by_identity():
    classes = _tensor_dataclasses()
    assert len(classes) > 20  # TrackerState, TrackResult, Template, Fragments, SolveResult, ...
    names = {c.__qualname__ for c in classes}
    assert {"LayerResult", "TrackedSequence"} <= names  # training_hooks' (their == raised as torchface's did)
    field_wise = [c.__qualname__ for c in classes if c.__dataclass_params__.eq]
    assert field_wise == []
    assert all(c.__hash__ is object.__hash__ for c in classes)  # hash agrees with ==


def test_a_result_compares_and_hashes_without_error():
    r = SolveResult(torch.zeros(2, 3), torch.ones(2), torch.ones(2), torch.zeros(2, dtype=torch.long),
                    torch.zeros(2, dtype=torch.long))  # fmt: skip
    same_tensors = dataclasses.replace(r)
    assert r == r and r != same_tensors and same_tensors in [r, same_tensors]
    assert len({r, same_tensors}) == 2


# --- Settings: one rule for flags and counts -------------------------------------------------------------------------
# A bool field takes a bool or a numpy bool (stored as bool); anything else is a TypeError naming the field ("no" was
# true). An int field takes an int or a numpy integer (stored as int); a float, a string or a bool is a TypeError
# naming the field (PyTorch's convention), a value out of range a ValueError.


def _settings() -> dict[type, dict]:
    """The settings dataclasses (and the synthetic clips' specs), each with the arguments it needs."""
    from torchface.job import JobConfig
    from torchface.solver.least_squares import SolverConfig
    from torchface.solver.robust import RobustLoss
    from torchface.synth.background import BackgroundSpec, OccluderSpec
    from torchface.synth.labelled import ClipSpec
    from torchface.template.dissimilarity import DissimilarityConfig
    from torchface.template.management import TemplateConfig
    from torchface.tracker.fit import FitConfig
    from torchface.tracker.lookahead import LookaheadConfig
    from torchface.tracker.smoothing import OneEuroConfig, SmoothingConfig
    from torchface.tracker.step import TrackerConfig
    from training_hooks.datasets import DatasetConfig
    from training_hooks.layer import LayerConfig
    from training_hooks.transforms import FaceTrackingConfig

    clip = dict(num_frames=4, width=64, height=48, distance_mm=600.0, ypr_deg=(0.0, 0.0, 0.0),
                translation_mm=(0.0, 0.0, 0.0), anim=torch.zeros(11), ambient=0.45, light_direction=(0.0, 0.0, -1.0),
                light_intensity=0.55)  # fmt: skip
    return {TrackerConfig: {}, FitConfig: {}, TemplateConfig: {}, DissimilarityConfig: {}, LookaheadConfig: {},
            SolverConfig: {}, JobConfig: {"out_dir": "out"}, DatasetConfig: {"clip_length": 4}, LayerConfig: {},
            FaceTrackingConfig: {}, ClipSpec: clip, OneEuroConfig: {}, SmoothingConfig: {}, RobustLoss: {},
            BackgroundSpec: {}, OccluderSpec: {"first_frame": 1, "last_frame": 3}}  # fmt: skip


#: A valid value of the int fields whose default is None.
_VALID_FOR_NONE = {"clip_stride": 2, "min_separation": 5, "shape_units": (0, 2), "sparse_landmark_count": 20}


def _kinds(cls: type) -> dict[str, str]:
    """``{field: "bool" | "int" | "ints"}`` of the flag, count and count-tuple fields of ``cls``."""
    kinds = {}
    for f in dataclasses.fields(cls):
        t = str(f.type).replace(" | None", "")
        if t in ("bool", "int"):
            kinds[f.name] = t
        elif t == "tuple[int, ...]":
            kinds[f.name] = "ints"
    return kinds


def test_every_config_dataclass_is_among_the_checked_settings():
    """A new ``...Config`` joins :func:`_settings` (and so the tests below)."""
    configs = set()
    packages = [(torchface.__path__, "torchface."), (training_hooks.__path__, "training_hooks.")]
    for info in (i for path, prefix in packages for i in pkgutil.walk_packages(path, prefix)):
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if inspect.isclass(obj) and dataclasses.is_dataclass(obj) and obj.__module__ == module.__name__:
                if name.endswith("Config") and _kinds(obj):
                    configs.add(obj)
    assert configs and configs <= set(_settings())


def test_bool_settings_take_bools_and_numpy_bools_only():
    """``TrackerConfig(use_illumination="x")``, ``JobConfig(convert="no")``, ``LayerConfig(keep_expression=1)`` and
    the like were taken (as true, or as what a later ``if`` made of them); ``TemplateConfig`` alone checked."""
    checked = 0
    for cls, base in _settings().items():
        for name, kind in _kinds(cls).items():
            if kind != "bool":
                continue
            default = getattr(cls(**base), name)
            for bad in ("no", 1, 0, None):
                with pytest.raises(TypeError, match=rf"\b{name} must be a bool"):
                    cls(**{**base, name: bad})
            got = getattr(cls(**{**base, name: np.bool_(not default)}), name)
            assert type(got) is bool and got is (not default), (cls.__name__, name)
            checked += 1
    assert checked >= 20


def test_int_settings_refuse_other_types_as_type_errors_and_take_numpy_integers():
    """A float, string or bool count was a ValueError in some settings ("max_frames must be an int >= 2") and a
    TypeError in others, or was taken (``JobConfig(normalised_size=128.0)``, ``LayerConfig(unrolled_levels=1.0)``,
    ``LookaheadConfig(min_keyframes=True)``, ``DatasetConfig(seed=None)``); numpy integers were refused by some
    (``max_batch``, ``TemplateConfig``'s counts) and kept as numpy scalars by others. A 0-d integer tensor or array is
    taken as its int (it was refused, where a number setting took a 0-d real one)."""
    checked = 0
    for cls, base in _settings().items():
        for name, kind in _kinds(cls).items():
            if kind == "bool":
                continue
            value = getattr(cls(**base), name)
            value = _VALID_FOR_NONE[name] if value is None else value
            if kind == "int":  # (a 0-d float or bool tensor is not a count either; a 0-d integer one is, as below)
                bads: tuple = (float(value), str(value), True, torch.tensor(float(value)), torch.tensor(True))
                numpy_value: object = np.int64(value)
            else:
                bads = ((float(value[0]), *value[1:]), (str(value[0]), *value[1:]), (True, *value[1:]))
                numpy_value = tuple(np.int64(v) for v in value)
            for bad in bads:
                with pytest.raises(TypeError, match=rf"\b{name}(\[0\])? must be an int"):
                    cls(**{**base, name: bad})
            if kind == "int":  # (one that requires grad is a float one, refused as such: it was told to pass float(x))
                wanted = rf"\b{name} must be an int[^;]*, got Tensor tensor\(2\.50*, requires_grad=True\)$"
                with pytest.raises(TypeError, match=wanted):
                    cls(**{**base, name: torch.tensor(2.5, requires_grad=True)})
            got = getattr(cls(**{**base, name: numpy_value}), name)
            if kind == "int":
                assert type(got) is int and got == value, (cls.__name__, name)
                for zero_d in (torch.tensor(value), np.array(value)):  # (refused before, where a 0-d real was taken)
                    got = getattr(cls(**{**base, name: zero_d}), name)
                    assert type(got) is int and got == value, (cls.__name__, name, zero_d)
            else:
                assert type(got) is tuple and all(type(v) is int for v in got) and got == tuple(value), (cls.__name__, name)
                for one_d in (torch.tensor(value), np.array(value)):  # (as a tuple of reals takes one; refused before)
                    got = getattr(cls(**{**base, name: one_d}), name)
                    assert type(got) is tuple and all(type(v) is int for v in got) and got == tuple(value), name
                with pytest.raises(TypeError, match=rf"\b{name}\[0\] must be an int"):
                    cls(**{**base, name: torch.tensor(value, dtype=torch.float64)})
            checked += 1
    assert checked >= 35


# --- Settings: the same rule for numbers -----------------------------------------------------------------------------
# A float field takes an int or a float (kept as given: an int stays an int, so that the repr, a training_hooks cache
# key, does not change) or a numpy real number (stored as a Python float); a string, a bool or another type is a
# TypeError naming the field.


def _reals(cls: type) -> dict[str, bool]:
    """``{field: optional}`` of the number fields of ``cls`` (``float``, or ``float | None``)."""
    return {f.name: "None" in str(f.type) for f in dataclasses.fields(cls)
            if str(f.type).replace(" | None", "") == "float"}  # fmt: skip


def test_real_settings_refuse_other_types_as_type_errors_naming_them():
    """A string for a number was refused with a message naming no setting (``TemplateConfig(texture_blend="0.5")``:
    "'<' not supported between instances of 'int' and 'str'", ``TrackerConfig(crop_margin="0.2")``: "must be real
    number, not str"), as a ValueError (``robust_c="4.685"``), or taken (``SolverConfig(step_tolerance="1e-8")``,
    ``LayerConfig(margin="0.05")``, ``FaceTrackingConfig(focal="300")``); a bool was taken as 0 or 1. A 0-d real
    tensor is taken as its Python number (it was "must be a real number, got Tensor" where a Python number was taken;
    bool and complex ones, a 1-element 1-D one, one that requires grad (its gradient was dropped silently) and a meta
    one are refused)."""
    checked = 0
    for cls, base in _settings().items():
        for name, optional in _reals(cls).items():
            bads: tuple = ("0.5", True, np.bool_(False), [0.5], torch.tensor(True), torch.tensor(0.5 + 0j),
                           torch.tensor([0.5]), torch.tensor(0.5, requires_grad=True),
                           torch.empty((), device="meta")) + (() if optional else (None,))
            for bad in bads:
                with pytest.raises(TypeError, match=rf"\b{name} must be a real number"):
                    cls(**{**base, name: bad})
            value = getattr(cls(**base), name)
            if value is not None:  # a numpy number is taken, as a Python float; a 0-d tensor as its Python number
                got = getattr(cls(**{**base, name: np.float32(value)}), name)
                assert type(got) is float and got == float(np.float32(value)), (cls.__name__, name)
                got = getattr(cls(**{**base, name: torch.tensor(value, dtype=torch.float64)}), name)
                assert type(got) is float and got == value, (cls.__name__, name)
                if type(value) is int:  # (an integer tensor: an int, as an int stays one)
                    got = getattr(cls(**{**base, name: torch.tensor(value)}), name)
                    assert type(got) is int and got == value, (cls.__name__, name)
            checked += 1
    assert checked >= 60


def test_real_settings_keep_ints_and_the_default_reprs():
    """An int for a number stays accepted and unchanged (the repr of a config is ``training_hooks``' cache key and
    the CLI's resume record); a numpy one was kept as a numpy scalar (``FitConfig`` refused a float32, and a
    ``torch.Tensor`` setting took a numpy float32 of ``held_shape_precision`` in no assignment)."""
    from torchface.tracker.fit import FitConfig
    from torchface.tracker.step import TrackerConfig
    from training_hooks.transforms import FaceTrackingConfig

    config = TrackerConfig(robust_c=5, crop_margin=0, min_face_width_px=np.int64(20))
    assert type(config.robust_c) is int and "robust_c=5, " in repr(config) and "crop_margin=0, " in repr(config)
    assert type(config.min_face_width_px) is float and config == TrackerConfig(robust_c=5.0, crop_margin=0.0)
    text = repr(FaceTrackingConfig(face_margin=0, focal=300))
    assert "face_margin=0, " in text and "focal=300, " in text
    assert FitConfig(held_shape_precision=np.float32(256.0)).held_shape_precision == 256.0


def test_settings_that_hold_settings_or_names_refuse_other_types_naming_them():
    """``JobConfig`` took anything as its ``tracker``, ``lookahead``, ``detector`` and ``device``: ``lookahead="yes"``
    was an AttributeError ("'str' object has no attribute 'max_frames'") once its videos were opened; the other
    settings already refused a nested setting of another type when made. Now every one does, naming the field."""
    checked = 0
    for cls, base in _settings().items():
        made = cls(**base)
        for f in dataclasses.fields(cls):
            value = getattr(made, f.name)
            if not (dataclasses.is_dataclass(value) or f.name in ("lookahead", "detector", "device")):
                continue
            for bad in ({}, 3.5):
                with pytest.raises(TypeError, match=rf"^{f.name} must be"):
                    cls(**{**base, f.name: bad})
            checked += 1
    assert checked >= 8


def test_settings_that_take_a_config_or_none_say_what_a_bool_is():
    """The command line's switches (``--smooth``, ``--lookahead``, ``--no-online-refine``) lead a user to write
    ``JobConfig(smoothing=True)`` or ``FaceTracker(refine_first=False)``, which were told the type alone ("must be a
    SmoothingConfig or None, got bool"); now the message says what on and off are, and where the config imports
    from. Another type is told as before."""
    from torchface.job import JobConfig
    from torchface.tracker import FaceTracker, SmoothingConfig
    from training_hooks import FaceTrackingConfig

    job = {"out_dir": "r", "landmarks": ("a.csv",)}
    makers = {
        "refine_first": (lambda v: FaceTracker(refine_first=v), "LookaheadConfig"),
        "refine_first ": (lambda v: JobConfig(**job, refine_first=v), "LookaheadConfig"),
        "refine_first  ": (lambda v: FaceTrackingConfig(refine_first=v), "LookaheadConfig"),
        "lookahead": (lambda v: JobConfig(**job, lookahead=v), "LookaheadConfig"),
        "smoothing": (lambda v: JobConfig(**job, smoothing=v), "SmoothingConfig"),
        "expression": (lambda v: SmoothingConfig(expression=v), "OneEuroConfig"),
    }
    for name, (make, config) in makers.items():
        for value in (True, False):
            with pytest.raises(TypeError) as refused:
                make(value)
            assert str(refused.value) == (f"{name.strip()} must be a {config} or None, got bool: on is {config}() (its "
                                          "defaults; from torchface.tracker), off is None")
        with pytest.raises(TypeError, match=rf"^{name.strip()} must be a {config} or None, got str$"):
            make("yes")


def test_settings_of_several_numbers_refuse_other_types_naming_them():
    """The settings that hold a tuple of numbers took a string as its characters (``TrackerConfig(
    expression_prior_weights="1" * 11)``: eleven ones, silently; bytes: their codes, 49.0), a bool element as 0 or 1
    (``robust_scale_floor=(True, True)``: floors of 1) and a string element was "'<' not supported between instances
    of 'int' and 'str'", naming no setting (``robust_scale_floor``, ``TemplateConfig.search_depth_factors``). Now
    each is a TypeError naming the setting (and the element); a list, numpy array or tensor of numbers is taken, as
    a tuple, and a default's repr is unchanged."""
    checked = 0
    for cls, base in _settings().items():
        default = cls(**base)
        for f in dataclasses.fields(cls):
            if not str(f.type).startswith("tuple[float"):
                continue
            value = getattr(default, f.name)
            value = (1.0,) * 11 if value is None else value  # (expression_prior_weights: CANDIDE-3's 11 units)
            grad = torch.tensor(value, dtype=torch.float64, requires_grad=True)  # (its gradient was dropped silently)
            for bad in ("1" * len(value), b"1" * len(value), ("0.5", *value[1:]), (True, *value[1:]), 3.0, grad):
                message = rf"^{f.name}(\[0\])? must be (a (tuple of )?real number|three numbers)"
                with pytest.raises(TypeError, match=message):
                    cls(**{**base, f.name: bad})
            # (0-d elements, as iterating a tensor or array gives them, were taken before: float(w), f > 0)
            tensor = torch.tensor(value, dtype=torch.float64)
            for same in (list(value), np.array(value), tensor, tuple(tensor), tuple(np.array(v) for v in value)):
                if cls.__name__ == "ClipSpec":  # (a test clip's spec keeps what it is given)
                    cls(**{**base, f.name: same})
                    continue
                assert getattr(cls(**{**base, f.name: same}), f.name) == tuple(value), (cls.__name__, f.name)
            with pytest.raises(TypeError, match=message):
                cls(**{**base, f.name: (torch.tensor(True), *value[1:])})  # (a 0-d bool: not a number either)
            if f.default is not dataclasses.MISSING:  # (the default's repr: part of training_hooks' cache key)
                assert repr(getattr(default, f.name)) == repr(f.default), (cls.__name__, f.name)
            checked += 1
    assert checked >= 5
    from torchface.tracker.fit import FitConfig

    with pytest.raises(ValueError, match="^held_shape_precision must be a finite number >= 0, got -1.0$"):
        FitConfig(held_shape_precision=-1.0)  # (the message named none: "prior precisions must be ...")


# --- Settings: ranges and choices ------------------------------------------------------------------------------------
# A number lies in its range (check_number: each field's interval stated once), which is finite unless its
# documentation gives inf a meaning, and NaN lies in none: ">= 0" and "> 0" alone had taken inf as a tolerance, a
# scale, a focal length or a threshold (search_step_px, max_damping, FaceTrackingConfig.focal, ...), and "< 0" NaN.
# A choice is a member of its enum; a string or another value is a TypeError naming the member the string spells (or
# every member) and the module to import the enum from (check_choice).

#: ``(class, field)`` of the number settings whose documentation gives ``inf`` a meaning ("no limit"); none does.
_INF_MEANS: set[tuple[str, str]] = set()


def _number_fields(cls: type) -> list[str]:
    """The fields of ``cls`` that hold a number or numbers (``float``, ``float | None``, tuples of floats, and
    ``FitConfig.shape_prior_precision``'s one number or one per unit)."""
    return [f.name for f in dataclasses.fields(cls) if "float" in str(f.type)]


@pytest.mark.parametrize("bad, error", [(math.nan, ValueError), (math.inf, ValueError), (-math.inf, ValueError),
                                        ("1", TypeError)], ids=["nan", "inf", "-inf", "str"])  # fmt: skip
def test_number_settings_refuse_nan_infinities_and_strings_naming_them(bad, error):
    """Every number field of every setting, as one number or as the first of several: NaN and an infinite value are
    ValueErrors and a string a TypeError (``FitConfig(shape_prior_precision="2")`` was a ValueError), each naming the
    field (and the element)."""
    wrong, checked = [], 0
    for cls, base in _settings().items():
        made = cls(**base)
        for name in _number_fields(cls):
            value = getattr(made, name)
            value = (1.0,) * 11 if value is None and "tuple" in str(cls.__dataclass_fields__[name].type) else value
            given = (bad, *value[1:]) if isinstance(value, tuple) else bad
            checked += 1
            if (cls.__name__, name) in _INF_MEANS and bad == math.inf:
                assert getattr(cls(**{**base, name: given}), name) == given, (cls.__name__, name)
                continue
            try:
                cls(**{**base, name: given})
            except error as e:
                if not re.match(rf"{name}(\[0\])? must be ", str(e)):
                    wrong.append(f"{cls.__name__}.{name}: {e}")
            except Exception as e:  # (the wrong kind of error)
                wrong.append(f"{cls.__name__}.{name}: {type(e).__name__} {e}")
            else:
                wrong.append(f"{cls.__name__}.{name}: {given!r} taken")
    assert wrong == []
    assert checked >= 80


def test_check_number_reads_its_interval_as_written_and_refuses_an_empty_or_mistyped_one():
    """``check_number``'s interval (torchface.extending: other packages write their own): its ends open or closed as
    written, spaces or none, and a closed ``inf`` end takes ``inf``. One that holds no number (``"[1, 0]"``,
    ``"(0, 0]"``, a NaN bound) refused every value, saying the empty range; a mistyped one was float()'s "could not
    convert string to float" at a value, and nothing at None. Now both are refused, naming the interval."""
    from torchface.extending import check_number

    assert [check_number(v, "x", "(0,1]") for v in (1, 0.5)] == [1, 0.5]
    assert check_number(math.inf, "x", "[0, inf]") == math.inf and check_number(-1, "x", "[-1, -1]") == -1
    for value, interval in ((0, "(0,1]"), (math.inf, "[0, inf)"), (-math.inf, "(-inf, 0]"), (math.nan, "[-inf, inf]")):
        with pytest.raises(ValueError, match=r"^x must be "):
            check_number(value, "x", interval)
    for interval in ("[1, 0]", "(0, 0]", "[0, 0)", "(nan, 1]", "[0, 1", "0, 1", "[0,,1]", "[0, 1, 2]", "[a, 1]"):
        for value in (0.5, None):
            with pytest.raises(ValueError, match=rf"^interval must be .*, got {re.escape(repr(interval))}$"):
                check_number(value, "x", interval, optional=True)


def _choice_fields(cls: type) -> dict[str, type[enum.Enum]]:
    """``{field: enum}`` of the fields of ``cls`` that hold an enum member."""
    names = vars(sys.modules[cls.__module__])
    kinds = {f.name: names.get(str(f.type)) for f in dataclasses.fields(cls)}
    return {name: k for name, k in kinds.items() if inspect.isclass(k) and issubclass(k, enum.Enum)}


def test_choice_settings_and_arguments_name_the_member_to_pass_and_where_it_imports_from():
    """A string for a choice was "must be a FaceStorage, got str" (``LayerMode``, ``UnrollStart``, ``RankBalance``,
    ``SolverMethod``, ``RobustKind``, ``load_candide3(animation=)``; a ``backend`` argument "got 'native'"): only
    ``TrackerConfig``'s said what to pass. Now every one names the member its value or name spells (any case), or
    every member, and the module the message names exports the enum."""
    from torchface.backend import Backend
    from torchface.geometry.camera import Intrinsics
    from torchface.model.candide import AnimationSet, load_candide3
    from torchface.rendering.rasterizer import rasterize_coverage

    verts = torch.tensor([[[0.0, 0.0, 500.0], [10.0, 0.0, 500.0], [0.0, 10.0, 500.0]]])
    faces = torch.tensor([[0, 1, 2]])
    calls = [(lambda v: load_candide3(animation=v), "animation", AnimationSet),
             (lambda v: rasterize_coverage(verts, faces, Intrinsics.default(16, 16), backend=v), "backend", Backend)]
    for cls, base in _settings().items():
        calls += [(lambda v, c=cls, b=base, n=name: c(**{**b, n: v}), name, kind)
                  for name, kind in _choice_fields(cls).items()]  # fmt: skip
    for make, name, kind in calls:
        must = rf"^{name} must be an? {kind.__name__}, got "
        for member in kind:
            for spelled in (str(member.value).upper(), f" {member.name.lower()}"):
                with pytest.raises(TypeError, match=must + rf"str '{spelled}' \(pass {kind.__name__}\.{member.name}, "
                                                           r"from [\w.]+\)$") as caught:  # fmt: skip
                    make(spelled)
        home = re.search(r"from ([\w.]+)\)$", str(caught.value))[1]
        assert getattr(importlib.import_module(home), kind.__name__) is kind, (name, home)
        every = re.escape(" or ".join(f"{kind.__name__}.{m.name}" for m in kind))
        for bad in ("gauss-newton", None, 1):
            with pytest.raises(TypeError, match=must + rf"{type(bad).__name__} .*\(pass {every}, from {home}\)$"):
                make(bad)
    assert {kind.__name__ for _, _, kind in calls} >= {"TrackSolver", "Backend", "RobustKind", "SolverMethod",
                                                        "LayerMode", "UnrollStart", "FaceStorage", "RankBalance",
                                                        "AnimationSet"}  # fmt: skip
