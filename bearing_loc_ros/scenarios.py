"""Where scenario files are found: one lookup for the simulator node and every CLI verb.

A scenario is named by a path (absolute, or relative to the working directory) or by the
name of a shipped scenario (``seed000.yaml``, or ``seed000`` without the extension).
"""

import os

PACKAGE = 'bearing_loc_ros'
#: Directory holding the package directory when running from a source checkout.
SOURCE_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class ScenarioNotFoundError(ValueError):
    """No scenario file of that name; ``problem`` says what was looked for and where."""

    def __init__(self, problem):
        super().__init__(f'scenario: {problem}')
        self.problem = problem


def _share_directory():
    """The package's installed share directory, or None when it is not installed."""
    try:
        from ament_index_python.packages import get_package_share_directory
        return get_package_share_directory(PACKAGE)
    except Exception:  # not installed with its ament index entry: no share candidates
        return None


def scenario_candidates(name, cwd=None):
    """Paths tried for scenario ``name``, in order.

    Absolute ``name``: itself. Relative: ``<cwd>/<name>``, then the source checkout
    (``<root>/<name>``, ``<root>/config/scenarios/<name>``), then the installed share
    directory (``<share>/<name>``, ``<share>/config/scenarios/<name>``). A name with no
    ``.yaml``/``.yml`` extension is also tried with ``.yaml`` appended, after the name itself.
    """
    name = os.path.expanduser(name)
    names = [name]
    if os.path.splitext(name)[1].lower() not in ('.yaml', '.yml'):
        names.append(name + '.yaml')
    if os.path.isabs(name):
        return names
    roots = [cwd or os.getcwd(), SOURCE_ROOT]
    share = _share_directory()
    if share is not None:
        roots.append(share)
    out = []
    for root in roots:
        for sub in ('', os.path.join('config', 'scenarios')):
            for n in names:
                c = os.path.join(root, sub, n)
                if c not in out:
                    out.append(c)
    return out


def resolve_scenario(name, cwd=None):
    """Path of the scenario file named ``name`` (see :func:`scenario_candidates`).

    Returns the first candidate that is a file. Raises ScenarioNotFoundError (a ValueError
    whose message starts with ``scenario:``) when ``name`` is empty or no candidate exists.
    """
    if not name:
        raise ScenarioNotFoundError('required: path or name of a scenario YAML, for example '
                                    'config/scenarios/seed000.yaml or seed000')
    candidates = scenario_candidates(name, cwd)
    for c in candidates:
        if os.path.isfile(c):
            return c
    raise ScenarioNotFoundError(f'file not found: {name!r} (looked in: '
                                f'{", ".join(candidates)})')
