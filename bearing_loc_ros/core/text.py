"""Values in one-line error messages, kept short (no ROS).

An error line names the bad value, but a value can be huge: a YAML alias expands a list to
millions of items, a parameter may hold megabytes. :func:`short_repr` writes a few items and
characters, built without the whole repr.
"""

import reprlib

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 6
_REPR.maxlevel = 2


def short_repr(value):
    """repr of ``value`` with at most 6 items per container, 2 levels and about 60
    characters per string or other value (``reprlib``), e.g. ``[0, 1, 2, 3, 4, 5, ...]``."""
    return _REPR.repr(value)
