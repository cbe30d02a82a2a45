"""Former spellings of options, JSON keys and estimator names, kept for one release.

Each use prints one warning line on stderr (``bearing_loc: warning: ... is deprecated``) and
is then treated as the current name. CHANGELOG.md lists every change and its replacement.
"""

import argparse
import sys

#: TMA estimator names before they became the fusion node's (CHANGELOG "Unreleased").
OLD_TMA_NAMES = {'ple': 'tma_ple', 'ctls': 'tma_ctls', 'ctls6': 'tma_ctls6', 'mle': 'tma_mle'}


def warn(old, new):
    """One stderr line saying ``old`` is deprecated in favour of ``new``."""
    print(f'bearing_loc: warning: {old} is deprecated, use {new} (the old spelling is '
          'accepted until the next release)', file=sys.stderr, flush=True)


class DeprecatedOption(argparse.Action):
    """argparse action of a former option spelling: warn, convert, store into ``dest``.

    ``replacement`` is the current option string named in the warning; ``convert`` maps the
    given (already type-converted) value to the current option's value (for a change of unit,
    for example mrad to degrees).
    """

    def __init__(self, option_strings, dest, replacement=None, convert=None, **kwargs):
        kwargs.setdefault('help', argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kwargs)
        self.replacement = replacement
        self.convert = convert

    def __call__(self, parser, namespace, values, option_string=None):
        """Warn about ``option_string`` and store the converted value (the use is recorded
        for :func:`conflict`)."""
        warn(option_string, self.replacement)
        setattr(namespace, self.dest, self.convert(values) if self.convert else values)
        uses = getattr(namespace, 'deprecated_uses', None) or []
        setattr(namespace, 'deprecated_uses', uses + [(option_string, self.replacement)])


def conflict(args, argv):
    """An error message when a deprecated option and its replacement were both given on
    the command line ``argv`` (the later one would silently win), else None."""
    for old, new in getattr(args, 'deprecated_uses', None) or ():
        # argparse takes an unambiguous prefix of an option (--sigma-de) for it
        if any(a.startswith('--') and len(a.split('=')[0]) > 2
               and new.startswith(a.split('=')[0]) for a in argv):
            return f'{old}: give only {new} (the deprecated {old} is also given)'
    return None


def json_key(doc, old, new, where=''):
    """Move ``doc[old]`` to ``doc[new]`` with a warning (both given: an error, ValueError)."""
    if isinstance(doc, dict) and old in doc:
        if new in doc:
            raise ValueError(f'{where}{old}: give only "{new}" (the deprecated "{old}" is also '
                             'present)')
        warn(f'JSON key "{where}{old}"', f'"{where}{new}"')
        doc[new] = doc.pop(old)
    return doc


def tma_estimator(name):
    """Current name of TMA estimator ``name`` (a former short name warns)."""
    if isinstance(name, str) and name in OLD_TMA_NAMES:
        warn(f'TMA estimator name {name!r}', repr(OLD_TMA_NAMES[name]))
        return OLD_TMA_NAMES[name]
    return name
