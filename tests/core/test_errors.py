"""Errors name the library's settings; a command front end words them as its own options."""

from __future__ import annotations

from dbb_capture.core.errors import DbbError, InputError


def test_settings_read_as_their_names_in_the_library_and_as_flags_when_worded():
    e = InputError("{=crop_size} 48: expected 16..1024 pixels; or pass {=overwrite}")
    assert str(e) == "crop_size 48: expected 16..1024 pixels; or pass overwrite"
    flags = {"crop_size": "--crop-size"}
    assert e.worded(lambda n: flags.get(n, n)) == "--crop-size 48: expected 16..1024 pixels; or pass overwrite"


def test_other_braces_are_left_alone():
    e = DbbError('object.json must be {"center": [x, y, z], "radius": r}')
    assert str(e) == 'object.json must be {"center": [x, y, z], "radius": r}'
