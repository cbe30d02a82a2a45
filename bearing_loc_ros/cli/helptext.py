"""Plain-text help for every verb: a description, one example, no markup from docstrings.

Also lets a comma-separated number list start with a minus sign without '='
(``--area-km -10,10,-10,10``), which argparse would otherwise take for an option.
"""

import argparse
import re
import textwrap

#: The top-level description and example.
DESCRIPTION = ('Networked direction finding from the command line: localize emitters from '
               'bearings, plan station layouts, evaluate estimators, and record, replay and '
               'process bags.')
TOP_EXAMPLE = 'bearing_loc plan map --scenario seed000 --altitude 5000 --png map.png'
TOP_EPILOG = ('Run "bearing_loc VERB --help" for the options of a verb. Exit codes: 0 success, '
              '2 bad input or an output that cannot be written (one line on stderr naming '
              'the field or flag), 1 other failure.')

#: One example command line per verb.
EXAMPLES = {
    'locate': 'bearing_loc locate bearings.json --estimator wmle --indent 1',
    'tma': 'bearing_loc tma observations.json --estimator tma_ctls --speed 380',
    'plan': 'bearing_loc plan place --scenario seed000 --sigma-deg 0.086 --altitude 5000 '
            '--area-km -20,40,-20,30',
    'evaluate': 'bearing_loc evaluate --scenario seed003 --estimator ls,mle,wmle '
                '--sigma-deg 0.5,1,2 --trials 200 --out results',
    'bag': 'bearing_loc bag simulate --scenario seed000 --duration 30 --out run1',
    'calibrate': 'bearing_loc calibrate --station s1=s1.csv --station s2=s2.csv '
                 '--params stations.yaml --transmitter 1200 350 20 --out calibrated.yaml',
    'view': 'bearing_loc view --bag run1',
}

_ROLE = re.compile(r':[a-z]+:`~?([^`]*)`')
_LITERAL = re.compile(r'``([^`]*)``')
_TICK = re.compile(r'`([^`]*)`')
#: A comma-separated list of numbers that starts with a minus sign.
_NEGATIVE_LIST = re.compile(r'^-[0-9.][0-9.eE+\-]*[,;]')


def plain(text):
    """``text`` without reStructuredText markup (roles, literals, back-quotes, ``::``)."""
    if not text:
        return text
    text = _ROLE.sub(lambda m: m.group(1).rsplit('.', 1)[-1], text)
    text = _LITERAL.sub(r'\1', text)
    text = _TICK.sub(r'\1', text)
    return text.replace('::', ':')


def fill(text, width=79):
    """Paragraphs (blank-line separated) wrapped to ``width``."""
    paras = [' '.join(p.split()) for p in re.split(r'\n\s*\n', text.strip())]
    return '\n\n'.join(textwrap.fill(p, width) for p in paras if p)


def example_epilog(example, extra=None):
    """Epilog text: ``example:`` and the indented command line (and ``extra`` below it)."""
    text = f'example:\n  {example}'
    return text + ('\n\n' + fill(extra) if extra else '')


def verb_parser(sub, verb, summary):
    """Sub-parser of ``verb``: summary as help and default description, its example."""
    return sub.add_parser(verb, help=summary, description=summary,
                          epilog=example_epilog(EXAMPLES[verb]) if verb in EXAMPLES else None,
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def sub_command(sub, name, summary, example, **kwargs):
    """A verb's sub-command parser (``bag play``, ``plan map``) with its example."""
    return sub.add_parser(name, help=summary, description=summary,
                          epilog=example_epilog(example),
                          formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)


def finish(parser):
    """Plain, wrapped description and plain help strings (after a verb added its options)."""
    if parser.description:
        parser.description = fill(plain(parser.description))
    for action in parser._actions:
        if action.help and action.help is not argparse.SUPPRESS:
            action.help = plain(action.help)


def join_negative_lists(argv):
    """``--opt -1,2`` -> ``--opt=-1,2`` for long options followed by a negative number list."""
    out = []
    for tok in argv:
        if (out and out[-1].startswith('--') and '=' not in out[-1]
                and _NEGATIVE_LIST.match(tok)):
            out[-1] = f'{out[-1]}={tok}'
        else:
            out.append(tok)
    return out
