"""Checks on error messages the tests share."""

from __future__ import annotations


def one_line(excinfo, name: str) -> str:
    """The message of a raised error (``pytest.raises`` excinfo), asserted to be one line naming ``name``."""
    msg = str(excinfo.value)
    assert "\n" not in msg and name in msg, msg
    return msg
