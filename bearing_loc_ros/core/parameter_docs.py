"""Renderers of the parameter schema (core.parameters): the Markdown tables of the docs and
the shipped parameter files, and the command line that prints or updates them. They take
the schema (a sequence of core.parameters.Param) as an argument and import nothing from
the package::

    python -m bearing_loc_ros.core.parameters --markdown fusion_node
    python -m bearing_loc_ros.core.parameters --yaml station_node > config/station.yaml
    python -m bearing_loc_ros.core.parameters --update-docs docs/nodes.md
"""

import argparse
import sys
import textwrap

#: Parameter types (the values of core.parameters' type constants) as the tables print them.
TYPE_NAMES = {'bool': 'bool', 'integer': 'int', 'double': 'double', 'string': 'string',
              'double_array': 'double[]', 'string_array': 'string[]'}


def _code(value):
    if isinstance(value, bool):
        return f'`{str(value).lower()}`'
    if isinstance(value, float):
        return f'`{value:g}`' if abs(value) < 1e-4 and value else f'`{value!r}`'
    if value == '':
        return "`''`"
    if isinstance(value, list):
        return '`[' + ', '.join(str(v) for v in value) + ']`'
    return f'`{value}`'


def _type_text(p):
    return TYPE_NAMES[p.type]


def _cell(text):
    return text.replace('|', '\\|')


def markdown_table(params):
    """The Markdown parameter table of the Params ``params`` (one row each, in order)."""
    rows = ['| name | type | default | unit | range | run time | description |',
            '|---|---|---|---|---|---|---|']
    for p in params:
        desc = p.description
        if p.deprecated:
            desc += ' (formerly ' + ', '.join(f'`{d}`' for d in p.deprecated) + \
                ', accepted with a deprecation warning)'
        rows.append(f'| `{p.name}` | {_type_text(p)} | {_code(p.default)} | {p.unit} | '
                    f'{_cell(p.range_text())} | {"no" if p.read_only else "yes"} | '
                    f'{_cell(desc)} |')
    return '\n'.join(rows) + '\n'


def _yaml_double(v):
    """A float as YAML 1.1 reads it back as a float (``1.0e-09``, not ``1e-09``)."""
    text = repr(float(v))
    mantissa, e, exp = text.partition('e')
    return f'{mantissa}.0e{exp}' if e and '.' not in mantissa else text


def _yaml_value(p, value):
    import yaml
    if p.type == 'double':
        return _yaml_double(value)
    if p.type == 'double_array':
        return '[' + ', '.join(_yaml_double(v) for v in value) + ']'
    if p.type == 'string' and value == '':
        return "''"
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()


def yaml_text(node, params):
    """The shipped parameter file of ``node`` with the Params ``params``: every parameter at
    its default (or its example value), each with its description, unit and range as a
    comment."""
    head = (f'# {node} parameters: every parameter with its default (or an example value).\n'
            '# Generated from the schema in bearing_loc_ros/core/parameters.py:\n'
            f'#   python -m bearing_loc_ros.core.parameters --yaml {node}\n'
            f'# Use: ros2 run bearing_loc_ros {node} --ros-args --params-file <this file>\n'
            '# `/**:` matches the node whatever its name and namespace. Doubles are written '
            'with a\n# decimal point (3.0); an integer is accepted for a double too.\n'
            '/**:\n  ros__parameters:\n')
    lines = []
    group = None
    for p in params:
        prefix, _, leaf = p.name.rpartition('.')
        indent = '    '
        if prefix:
            if prefix != group:
                lines.append(f'    {prefix}:')
                group = prefix
            indent = '      '
        else:
            group = None
        rng = p.range_text().replace('`', '')
        rng = (f'one of {rng}' if p.choices else f'range {rng}') if rng else ''
        extra = '; '.join(x for x in (p.unit, rng, '' if p.read_only else 'run time') if x)
        comment = p.description + (f' ({extra})' if extra else '')
        for c in textwrap.wrap(comment, 95 - len(indent)):
            lines.append(f'{indent}# {c}')
        value = p.default if p.example is None else p.example
        lines.append(f'{indent}{"# " if p.commented else ""}{leaf}: {_yaml_value(p, value)}')
    return head + '\n'.join(lines) + '\n'


def docs_region(text, node):
    """The text between ``<!-- BEGIN parameters <node> -->`` and ``<!-- END parameters
    <node> -->`` in ``text`` (None when the markers are absent)."""
    begin, end = f'<!-- BEGIN parameters {node} -->\n', f'<!-- END parameters {node} -->'
    i = text.find(begin)
    j = text.find(end, i + len(begin)) if i >= 0 else -1
    return None if j < 0 else text[i + len(begin):j]


def fill_docs(text, schemas):
    """``text`` with the parameter region of every node of ``schemas`` (node -> Params)
    replaced by its :func:`markdown_table`."""
    for node, params in schemas.items():
        old = docs_region(text, node)
        if old is not None:
            begin = f'<!-- BEGIN parameters {node} -->\n'
            text = text.replace(begin + old, begin + markdown_table(params), 1)
    return text


def main(schemas, argv=None):
    """``python -m bearing_loc_ros.core.parameters --markdown|--yaml NODE|--update-docs FILE``."""
    ap = argparse.ArgumentParser(prog='python -m bearing_loc_ros.core.parameters',
                                 description='Print a node parameter table or file.')
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument('--markdown', metavar='NODE', choices=tuple(schemas),
                      help='Markdown parameter table of NODE')
    what.add_argument('--yaml', metavar='NODE', choices=tuple(schemas),
                      help='parameter file of NODE (every parameter at its default)')
    what.add_argument('--update-docs', metavar='FILE',
                      help='rewrite the parameter-table regions of FILE in place')
    args = ap.parse_args(argv)
    if args.update_docs:
        with open(args.update_docs, encoding='utf-8') as f:
            text = f.read()
        with open(args.update_docs, 'w', encoding='utf-8') as f:
            f.write(fill_docs(text, schemas))
        return 0
    sys.stdout.write(markdown_table(schemas[args.markdown]) if args.markdown
                     else yaml_text(args.yaml, schemas[args.yaml]))
    return 0
