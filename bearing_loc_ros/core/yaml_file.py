"""YAML files of the package, read with one-line errors: its own formats (scenario files,
bag metadata) and the nodes' parameter files (``--params-file``, ``-p NAME:=VALUE``).

PyYAML follows YAML 1.1, where a float needs a dot and a signed exponent (``1e3`` and
``1.0e7`` are strings), ``010`` is octal 8, ``1:30`` is 90 (base 60) and ``1_000`` is 1000.
:func:`loader` (the package's own formats: scenario files, bag metadata) reads numbers as
YAML 1.2's core schema does instead: ``1e3`` is 1000.0, ``010`` is 10, and ``1:30`` or
``1_000`` are strings (which a number field then refuses). It also refuses a key given twice
in one mapping (YAML forbids it; PyYAML kept the last silently).

Every reader refuses a document whose aliases (``*name``) expand to more than
:data:`MAX_VALUES` values: a few hundred bytes of nested aliases ("billion laughs") expand
to 10⁹ values, which a program walking or printing the data cannot survive.

A parameter file must give the offline tools (``bag process --params-file``, ``calibrate``
and ``bag import --params``) exactly the values the nodes get, and rcl's parser is neither
YAML 1.1 nor 1.2 (rcl_yaml_param_parser, ROS 2 Jazzy; :func:`param_value`, tested against
rclpy). A quoted scalar is a string. An unquoted one is, in this order:

- a bool when it is one of ``y Y yes Yes YES true True TRUE on On ON`` (``n N no No NO
  false False FALSE off Off OFF`` for false);
- a double when it is YAML's ``.nan``, ``.NaN``, ``.NAN`` or ``[+-].inf``, ``.Inf``,
  ``.INF``;
- an integer when C's ``strtol`` (base 0: ``0x1F``; ``010`` is octal 8) reads all of it
  within int64;
- a double when ``strtod`` reads all of it without a range error (``nan``, ``inf``,
  ``Infinity``, ``0x1p3``, ``08``; ``1e400`` and the subnormal ``1e-310`` stay strings);
- else a string (``1_000``, ``12:30``, ``null`` and ``~`` are strings).

An empty value, an empty list and a list mixing types (``[1, 2.5]``) are errors.
:func:`params_loader` reads files so. Not followed: values with an explicit YAML tag
(``!!float 5`` is 5.0 here, 5 to rcl) and hexadecimal floats that are exactly subnormal
(a string here, a number to rcl).
"""

import re
import sys

#: YAML 1.2 core schema integers and floats (``1e3``, ``1.0e7``, ``2E-6``, ``.inf``, ``.nan``;
#: no ``_`` digit groups, no base-60 ``1:30``, ``010`` decimal).
_INT = re.compile(r'^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$')
_FLOAT = re.compile(r'''^(?:
    [-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?
  | [-+]?\.(?:inf|Inf|INF)
  | \.(?:nan|NaN|NAN))$''', re.X)
_INT_TAG = 'tag:yaml.org,2002:int'
_FLOAT_TAG = 'tag:yaml.org,2002:float'
#: Most values (mapping entries, list items and scalars, an alias counted each time it is
#: used) one YAML document may expand to. Real files hold thousands (a long waypoint list).
MAX_VALUES = 1_000_000
#: Largest YAML file read, bytes (8 MiB; PyYAML parses about 1 MB/s, and a scenario with
#: 10⁵ waypoints is about 4 MB). A larger file, or an endless one such as /dev/zero, is
#: refused before parsing.
MAX_BYTES = 8 * 1024 * 1024

_LOADER = None


def _no_duplicate_keys(loader, node):
    """ConstructorError at the second occurrence of a key of the mapping ``node``."""
    from yaml.constructor import ConstructorError
    seen = set()
    for key_node, _ in node.value:
        if key_node.tag == 'tag:yaml.org,2002:merge':
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            new = key not in seen
        except TypeError:                       # an unhashable key: the constructor says so
            return
        if not new:
            raise ConstructorError(None, None, f'key {str(key)[:60]!r} given twice in one '
                                   'mapping', key_node.start_mark)
        seen.add(key)


def _yaml12_int(loader, node):
    """An integer of YAML 1.2's core schema (``010`` is ten, ``0o10`` eight, ``0x10``
    sixteen)."""
    text = loader.construct_scalar(node)
    if text.startswith('0o'):
        return int(text[2:], 8)
    if text.startswith('0x'):
        return int(text[2:], 16)
    return int(text, 10)


def loader():
    """A ``yaml.SafeLoader`` subclass (plain data only, no Python objects) that reads numbers
    as YAML 1.2's core schema and refuses duplicate keys (module docstring)."""
    global _LOADER
    if _LOADER is None:
        import yaml      # here: the commands that read no YAML do not pay its import

        class Loader(yaml.SafeLoader):
            """SafeLoader with YAML 1.2 numbers and no duplicate keys."""

            def construct_mapping(self, node, deep=False):
                if isinstance(node, yaml.MappingNode):
                    _no_duplicate_keys(self, node)
                return super().construct_mapping(node, deep)

        Loader.yaml_implicit_resolvers = {
            first: [(tag, rx) for tag, rx in rules if tag not in (_INT_TAG, _FLOAT_TAG)]
            for first, rules in yaml.SafeLoader.yaml_implicit_resolvers.items()}
        Loader.add_implicit_resolver(_INT_TAG, _INT, list('-+0123456789'))
        Loader.add_implicit_resolver(_FLOAT_TAG, _FLOAT, list('-+0123456789.'))
        Loader.add_constructor(_INT_TAG, _yaml12_int)
        _LOADER = Loader
    return _LOADER


def check_expansion(doc, limit=MAX_VALUES):
    """``doc`` when it holds at most ``limit`` values counted as a tree (an object reached
    through several aliases counts each time), else ValueError. Stops counting at the limit,
    so a "billion laughs" document costs at most ``limit`` steps."""
    stack, count = [doc], 0
    while stack:
        v = stack.pop()
        count += 1
        if count > limit:
            raise ValueError(f'more than {limit:,} values once its aliases (*name) are '
                             'expanded')
        if isinstance(v, dict):
            stack.extend(v.keys())
            stack.extend(v.values())
        elif isinstance(v, list):
            stack.extend(v)
    return doc


#: Unquoted scalars rcl reads as booleans (any other capitalisation is a string).
_RCL_BOOLS = {**dict.fromkeys(('Y', 'y', 'yes', 'Yes', 'YES', 'true', 'True', 'TRUE', 'on',
                               'On', 'ON'), True),
              **dict.fromkeys(('N', 'n', 'no', 'No', 'NO', 'false', 'False', 'FALSE', 'off',
                               'Off', 'OFF'), False)}
#: What C's strtol (base 0) and strtod read in full (the text of a plain scalar has no
#: surrounding blanks).
_C_INT = re.compile(r'[-+]?(?:0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')
_C_DEC = re.compile(r'[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?')
_C_HEX = re.compile(r'[-+]?0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)'
                    r'(?:[pP][-+]?[0-9]+)?')
_C_SPECIAL = re.compile(r'[-+]?(?:inf(?:inity)?|nan(?:\([0-9A-Za-z_]*\))?)', re.I)
#: YAML's own forms, which rcl reads before strtod.
_YAML_SPECIAL = {**dict.fromkeys(('.nan', '.NaN', '.NAN'), float('nan')),
                 **{f'{sign}{inf}': float(f'{sign}inf') for sign in ('', '+', '-')
                    for inf in ('.inf', '.Inf', '.INF')}}
_INT64 = 2 ** 63
#: Tag of the unquoted scalars of a parameter file (typed by :func:`param_value`).
_PLAIN = 'tag:bearing_loc,2026:rcl-plain'


def _c_int(text):
    """strtol(text, base 0) when it reads all of ``text`` within int64, else None."""
    if not _C_INT.fullmatch(text):
        return None
    sign = -1 if text[0] == '-' else 1
    body = text.lstrip('+-')
    if body[:2] in ('0x', '0X'):
        v = int(body[2:], 16)
    elif body[0] == '0':
        v = int(body, 8)
    else:
        v = int(body)
    v *= sign
    return v if -_INT64 <= v < _INT64 else None


def _c_double(text):
    """strtod(text) when it reads all of ``text`` without ERANGE, else None."""
    if _C_SPECIAL.fullmatch(text):
        low = text.lower()
        return float('nan') if 'nan' in low else -float('inf') if low[0] == '-' else float('inf')
    if _C_DEC.fullmatch(text):
        v, mantissa, digits = float(text), re.split('[eE]', text)[0], '123456789'
    elif _C_HEX.fullmatch(text):
        try:
            v = float.fromhex(text)
        except OverflowError:                       # beyond the double range: ERANGE
            return None
        mantissa, digits = re.split('[pP]', text)[0].lstrip('+-')[2:], '123456789abcdefABCDEF'
    else:
        return None
    if v in (float('inf'), -float('inf')):
        return None                                 # overflow
    if abs(v) < sys.float_info.min and any(c in digits for c in mantissa):
        return None                                 # underflow, subnormal or to zero
    return v


def param_value(text):
    """The value rcl's parameter parser gives the unquoted scalar ``text`` (module docstring):
    bool, int, float or str; ``ValueError`` for an empty value."""
    if text == '':
        raise ValueError('no value')
    if text in _RCL_BOOLS:
        return _RCL_BOOLS[text]
    if text in _YAML_SPECIAL:
        return _YAML_SPECIAL[text]
    v = _c_int(text)
    if v is None:
        v = _c_double(text)
    return text if v is None else v


_PARAMS_LOADER = None


def params_loader():
    """A ``yaml.SafeLoader`` subclass reading a ROS 2 parameter file as rcl does (module
    docstring): unquoted scalars by :func:`param_value`, quoted ones and mapping keys as
    strings; a list must hold items of one type. Errors are ``yaml.YAMLError`` with the
    line."""
    global _PARAMS_LOADER
    if _PARAMS_LOADER is None:
        import yaml
        from yaml.constructor import ConstructorError

        class ParamsLoader(yaml.SafeLoader):
            """SafeLoader typing scalars as rcl_yaml_param_parser does."""

            def resolve(self, kind, value, implicit):
                if kind is yaml.ScalarNode and implicit[0]:
                    return _PLAIN
                return super().resolve(kind, value, implicit)

            def construct_mapping(self, node, deep=False):
                for key, _ in node.value:          # parameter and node names
                    if key.tag == _PLAIN:
                        key.tag = 'tag:yaml.org,2002:str'
                return super().construct_mapping(node, deep)

        def plain(loader, node):
            try:
                return param_value(node.value)
            except ValueError as exc:
                raise ConstructorError(None, None, str(exc), node.start_mark) from None

        def sequence(loader, node):
            items = loader.construct_sequence(node, deep=True)
            kinds = {bool if type(v) is bool else int if type(v) is int else
                     float if type(v) is float else str if type(v) is str else None
                     for v in items}
            if not items:
                raise ConstructorError(None, None, 'an empty list (ROS 2 cannot type it)',
                                       node.start_mark)
            if len(kinds) != 1 or None in kinds:
                raise ConstructorError(
                    None, None, 'a list must hold items of one type: bool, integer, float '
                    'or string (ROS 2 rejects [1, 2.5]; write [1.0, 2.5])', node.start_mark)
            return items

        ParamsLoader.add_constructor(_PLAIN, plain)
        ParamsLoader.add_constructor('tag:yaml.org,2002:seq', sequence)
        _PARAMS_LOADER = ParamsLoader
    return _PARAMS_LOADER


def load_param_text(text):
    """One value as ``-p NAME:=VALUE`` gives it to a node (:func:`params_loader`);
    ``yaml.YAMLError`` when rcl would refuse it."""
    import yaml
    return check_expansion(yaml.load(text, Loader=params_loader()))


def load_text(text):
    """One YAML document (a value such as ``1e-9`` or ``[1, 2]``) parsed by :func:`loader`;
    ``yaml.YAMLError`` when it is not valid YAML."""
    import yaml
    return check_expansion(yaml.load(text, Loader=loader()))


def read_yaml(path, label, kind='file', params=False):
    """The parsed document of the YAML file ``path`` (None when it is empty), by
    :func:`loader` (:func:`params_loader` with ``params``: a ROS 2 parameter file).

    Errors are ``ValueError`` of one line, prefixed ``label``: ``<label>: cannot read <kind>
    (<reason>)``, ``<label>: <kind> larger than <n> MiB`` (:data:`MAX_BYTES`), ``<label>: not
    a UTF-8 text file``, ``<label>: invalid YAML (<message, whitespace runs made one
    space>)``, also for a document beyond :data:`MAX_VALUES`.
    """
    import yaml
    try:
        with open(path, 'rb') as f:
            data = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise ValueError(f'{label}: cannot read {kind} ({exc.strerror or exc})') from None
    if len(data) > MAX_BYTES:
        raise ValueError(f'{label}: {kind} larger than {MAX_BYTES // 2 ** 20} MiB')
    try:
        return check_expansion(yaml.load(data.decode('utf-8'), Loader=params_loader()
                                         if params else loader()))
    except UnicodeDecodeError:
        raise ValueError(f'{label}: not a UTF-8 text file') from None
    except (yaml.YAMLError, ValueError) as exc:     # ValueError: a scalar's constructor
        raise ValueError(f'{label}: invalid YAML ({" ".join(str(exc).split())})') from None
