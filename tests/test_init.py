"""Tests of the package's own module (``torchface/__init__.py``): its public names and sub-packages, imported on
first use."""

from __future__ import annotations

import pytest

import torchface


def test_public_names_and_sub_packages_come_on_first_use():
    from torchface.tracker import FaceTracker, TrackResult

    assert torchface.FaceTracker is FaceTracker and torchface.TrackResult is TrackResult
    assert sorted(torchface.__all__) == [n for n in dir(torchface) if n in torchface.__all__]
    assert torchface.tracker.FaceTracker is FaceTracker  # a sub-package by its name
    with pytest.raises(AttributeError, match="module 'torchface' has no attribute 'nothing'"):
        torchface.nothing  # noqa: B018


@pytest.mark.parametrize("name", ["foo.bar", "tracker.step", "", "1tracker"])
def test_a_name_that_is_no_identifier_is_no_attribute(name):
    """An attribute lookup of a dotted name went to the import system: ``hasattr(torchface, "foo.bar")`` raised
    ModuleNotFoundError (hasattr catches AttributeError alone), and ``getattr(torchface, "tracker.step")`` gave the
    module ``torchface.tracker.step``."""
    assert not hasattr(torchface, name)
    with pytest.raises(AttributeError, match="module 'torchface' has no attribute"):
        getattr(torchface, name)
