"""The one error kind of the models package (apart from the model modules, which a logged model ships)."""

from __future__ import annotations

from ..errors import BronchoError


class ModelError(BronchoError, ValueError):
    """A bad architecture name, size, setting or pretrained file (also a ValueError for library callers)."""
