"""ROS 2 message definitions as ``ros2msg`` schemas (Foxglove, MCAP).

A ``ros2msg`` schema is the message's ``.msg`` text followed by the text of every message
it depends on, each introduced by a line of 80 ``=`` and ``MSG: <package>/<Type>`` (the
format rosbag2's MCAP storage and foxglove_bridge write). The ``.msg`` files are the ones
rosidl installed with the message packages, ``<prefix>/share/<package>/msg/<Type>.msg``
for each prefix of ``AMENT_PREFIX_PATH`` (the PyPI wheels install them under the
virtualenv). A type whose ``.msg`` is not installed falls back to the definition that
``rosbags``' Jazzy typestore generates (same fields, no comments or defaults).
"""

import os
import re

SEPARATOR = '=' * 80
#: Primitive field types of the ROS 2 interface definition language.
PRIMITIVES = frozenset((
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'))
_FIELD = re.compile(r'^\s*([A-Za-z][\w/]*)(?:<=\d+)?(?:\[[^\]]*\])?\s+\w')


def _prefixes():
    return [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]


def split_type(msgtype):
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'Type'); ValueError otherwise."""
    parts = msgtype.split('/')
    if len(parts) == 3 and parts[1] == 'msg':
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f'message type: expected pkg/msg/Type, got {msgtype!r}')


def msg_file(msgtype, prefixes=None):
    """Path of the installed ``.msg`` file of a type, or None."""
    pkg, name = split_type(msgtype)
    for prefix in (prefixes if prefixes is not None else _prefixes()):
        path = os.path.join(prefix, 'share', pkg, 'msg', name + '.msg')
        if os.path.isfile(path):
            return path
    return None


def dependencies(text, package):
    """Complex field types of a ``.msg`` text, in order of first use, as 'pkg/Type'.

    Constants (``TYPE NAME=value``) are primitives; a type without a package is in
    ``package`` (the ROS 2 rule).
    """
    out = []
    for line in text.splitlines():
        line = line.split('#', 1)[0]
        m = _FIELD.match(line)
        if not m:
            continue
        base = m.group(1)
        if base in PRIMITIVES:
            continue
        if '/' not in base:
            base = f'{package}/{base}'
        pkg, name = split_type(base)
        full = f'{pkg}/{name}'
        if full not in out:
            out.append(full)
    return out


def _rosbags_definition(msgtype):
    from . import bagio
    pkg, name = split_type(msgtype)
    text, _ = bagio.typestore().generate_msgdef(f'{pkg}/msg/{name}', ros_version=2)
    return text


def message_definition(msgtype, prefixes=None):
    """The flattened ``ros2msg`` definition (str) of a message type (module docstring).

    Dependencies are appended depth first in order of first use, each once. ValueError when
    neither the ``.msg`` file nor the typestore knows the type.
    """
    path = msg_file(msgtype, prefixes)
    if path is None:
        try:
            return _rosbags_definition(msgtype)
        except Exception as exc:  # rosbags raises its own TypesysError
            raise ValueError(f'{msgtype}: no message definition found ({exc})') from None
    with open(path, encoding='utf-8') as f:
        root = f.read()
    pkg, _ = split_type(msgtype)
    parts, seen = [root.rstrip('\n')], set()
    stack = list(reversed(dependencies(root, pkg)))
    while stack:
        dep = stack.pop()
        if dep in seen:
            continue
        seen.add(dep)
        dpath = msg_file(dep, prefixes)
        if dpath is None:
            text = _rosbags_definition(dep).split('\n' + SEPARATOR, 1)[0]
        else:
            with open(dpath, encoding='utf-8') as f:
                text = f.read()
        parts.append(f'{SEPARATOR}\nMSG: {dep}\n{text.rstrip()}')
        stack.extend(reversed([d for d in dependencies(text, split_type(dep)[0])
                               if d not in seen]))
    return '\n'.join(parts) + '\n'
