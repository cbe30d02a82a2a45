"""YAML as the ROS 2 parameter files read it: one file with one-line errors (scenario files,
bag metadata, CLI files) and single values (``-p NAME:=VALUE``).

PyYAML follows YAML 1.1, where a float needs a dot and a signed exponent: ``1e3`` and
``1.0e7`` are strings there, while rcl's parameter parser (as ``station_node
--params-file`` reads the same file) and YAML 1.2 read them as numbers. :func:`loader` adds
those exponent forms, so a number written that way gives the value the nodes see. (Other
YAML 1.1 forms PyYAML keeps, such as ``1_000`` or ``12:30``, rcl reads as strings.)
"""

import re

#: YAML 1.2 (core schema) floats, plus YAML 1.1's: an exponent no longer needs a dot or a
#: sign (``1e3``, ``1.0e7``, ``2E-6``), and ``.inf``/``.nan`` as before.
_FLOAT = re.compile(r'''^(?:
    [-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
  | [-+]?[0-9]+[eE][-+]?[0-9]+
  | [-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
  | [-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
  | [-+]?\.(?:inf|Inf|INF)
  | \.(?:nan|NaN|NAN))$''', re.X)

_LOADER = None


def loader():
    """A ``yaml.SafeLoader`` subclass (plain data only, no Python objects) that reads the
    YAML 1.2 float forms as floats (module docstring)."""
    global _LOADER
    if _LOADER is None:
        import yaml      # here: the commands that read no YAML do not pay its import

        class Loader(yaml.SafeLoader):
            """SafeLoader with YAML 1.2 floats."""

        Loader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT,
                                     list('-+0123456789.'))
        _LOADER = Loader
    return _LOADER


def load_text(text):
    """One YAML document (a value such as ``1e-9`` or ``[1, 2]``) parsed by :func:`loader`;
    ``yaml.YAMLError`` when it is not valid YAML."""
    import yaml
    return yaml.load(text, Loader=loader())


def read_yaml(path, label, kind='file'):
    """The parsed document of the YAML file ``path`` (None when it is empty), by
    :func:`loader`.

    Errors are ``ValueError`` of one line, prefixed ``label``: ``<label>: cannot read <kind>
    (<reason>)``, ``<label>: not a UTF-8 text file``, ``<label>: invalid YAML (<message,
    whitespace runs made one space>)``.
    """
    import yaml
    try:
        with open(path, encoding='utf-8') as f:
            return yaml.load(f, Loader=loader())
    except OSError as exc:
        raise ValueError(f'{label}: cannot read {kind} ({exc.strerror or exc})') from None
    except UnicodeDecodeError:
        raise ValueError(f'{label}: not a UTF-8 text file') from None
    except (yaml.YAMLError, ValueError) as exc:     # ValueError: a scalar's constructor
        raise ValueError(f'{label}: invalid YAML ({" ".join(str(exc).split())})') from None
