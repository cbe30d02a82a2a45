"""The ``bearing_loc`` command line tool: ``bearing_loc <verb> ...``.

Each verb lives in its own module ``bearing_loc_ros.cli.<verb>`` exposing
``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported lazily so that one
verb's optional dependencies (matplotlib, rosbags) never slow down or break another.

Exit codes: 0 success, 2 bad input (one line on stderr naming the field) or an output that
cannot be written (a file, or stdout: ``stdout: cannot write (...)``), 1 other failure. A
closed pipe on stdout (``bearing_loc locate big.json | head``) ends the command quietly.
"""

import argparse
import contextlib
import importlib
import os
import sys

VERBS = {
    'locate': 'Localize emitters from bearings (JSON in, JSON out).',
    'tma': 'Single moving station target motion analysis (JSON in, JSON out).',
    'plan': 'Station placement: cut angle, accuracy maps, placement.',
    'evaluate': 'Monte Carlo evaluation of estimators against the CRLB.',
    'bag': 'rosbag2 datasets: simulate, play, process, info, import.',
    'calibrate': 'Receiver heading biases and confidence->sigma from a calibration run.',
    'view': 'Foxglove WebSocket server of the live topics or of bags.',
}


class InputError(ValueError):
    """Bad user input: reported as one line on stderr with exit code 2."""


class OutputError(Exception):
    """stdout cannot be written (closed, disk full): one line on stderr, exit code 2.

    Not a ValueError or OSError, so that no handler of the verbs takes it for bad input or
    for a file of their own.
    """


@contextlib.contextmanager
def writing(flag, path):
    """Turn an OSError while writing ``path`` into an InputError naming ``flag``:
    ``<flag>: cannot write '<path>' (<reason>)``."""
    try:
        yield
    except OSError as exc:
        raise InputError(f'{flag}: cannot write {path!r} ({exc.strerror or exc})') from None


def read_input(path):
    """The bytes of the input file ``path`` ('-': stdin); InputError naming ``input`` when it
    cannot be read (also a closed stdin, ``bearing_loc locate <&-``)."""
    try:
        if path == '-':
            stream = getattr(sys.stdin, 'buffer', sys.stdin)
            if stream is None:
                raise InputError('input: cannot read stdin: it is closed')
            data = stream.read()
        else:
            with open(path, 'rb') as f:
                data = f.read()
    except OSError as exc:
        where = 'stdin' if path == '-' else repr(path)
        raise InputError(f'input: cannot read {where}: {exc.strerror or exc}') from None
    return data.encode('utf-8') if isinstance(data, str) else data


class _GuardedStdout:
    """``sys.stdout`` while a verb runs: an OSError writing it (disk full, a closed stdout)
    becomes :class:`OutputError`; BrokenPipeError (a reader that stopped, ``| head``) passes
    as it is. Everything else goes to the wrapped stream."""

    def __init__(self, stream):
        self._stream = stream

    def _call(self, name, *args):
        if self._stream is None:
            raise OutputError('stdout: cannot write (it is closed)')
        try:
            return getattr(self._stream, name)(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise OutputError(f'stdout: cannot write ({exc.strerror or exc})') from None

    def write(self, text):
        return self._call('write', text)

    def writelines(self, lines):
        return self._call('writelines', lines)

    def flush(self):
        return None if self._stream is None else self._call('flush')

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _silence_stdout():
    """Point file descriptor 1 at /dev/null after stdout failed, so that the interpreter's
    flush at exit of what is still buffered neither fails again nor prints "Exception
    ignored" (the Python documentation's advice for SIGPIPE). Only for the process's own
    stdout (not a test's captured stream)."""
    if sys.__stdout__ is None:
        return
    try:
        fd = sys.__stdout__.fileno()
        devnull = os.open(os.devnull, os.O_WRONLY)
    except (OSError, ValueError):
        return
    try:
        os.dup2(devnull, fd)
    except OSError:
        pass
    finally:
        os.close(devnull)


def load_yaml(path, name, params=False):
    """The parsed YAML document of the file ``path`` (None when empty); with ``params`` a
    ROS 2 parameter file, typed as the nodes' parser types it (core.yaml_file).

    An unreadable file or invalid YAML is an :class:`InputError` ``<name>: ...`` naming the
    file (``name``: the option or parameter that gave the path).
    """
    from ..core.yaml_file import read_yaml
    try:
        return read_yaml(path, f'{name}: {path}', params=params)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def single_blas_thread():
    """Start OpenBLAS with one thread unless the user chose (``OPENBLAS_NUM_THREADS``).

    For the ``locate`` console command, before numpy is imported: its matrices are 3 × 3 to
    N × N, which OpenBLAS never splits across threads, while the threads it starts with
    numpy cost about 50 ms of CPU per run on a two-core machine. Changes this process's
    environment, so it is called only for the console script, not for ``main(argv)``.
    """
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


def _load(verb):
    return importlib.import_module(f'{__name__}.{verb}')


class OneLineParser(argparse.ArgumentParser):
    """argparse with the tool's error contract: a usage error is one line on stderr,
    ``<prog>: error: <message> (see <prog> --help)``, and exit code 2 (argparse prints the
    whole usage block first). Sub-parsers (verbs, ``bag play``) are of this class too."""

    def error(self, message):
        self.exit(2, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


def _prog_of(args, extra, before_verb):
    """The command an unrecognized argument belongs to: ``bearing_loc`` for one given
    before the verb, else the verb and its sub-command (``bearing_loc bag play``)."""
    if args.verb is None or extra[0] in before_verb:
        return 'bearing_loc'
    sub = getattr(args, f'{args.verb}_command', None)
    return ' '.join(['bearing_loc', args.verb] + ([sub] if sub else []))


def main(argv=None):
    """Entry point of the ``bearing_loc`` console script."""
    real = sys.stdout
    guarded = sys.stdout = _GuardedStdout(real)
    verb_seen = []
    try:
        try:
            code = _main(argv, verb_seen.append)
        except SystemExit as exc:       # --help: its text may still be buffered too
            code = exc
        guarded.flush()         # a write that was buffered fails here
        if isinstance(code, SystemExit):
            raise code
        return code
    except OutputError as exc:
        if real is sys.__stdout__:
            _silence_stdout()
        prog = ' '.join(['bearing_loc'] + verb_seen[-1:])
        print(f'{prog}: error: {exc}', file=sys.stderr)
        return 2
    except BrokenPipeError:
        if real is sys.__stdout__:
            _silence_stdout()
        return 0
    finally:
        if sys.stdout is guarded:
            sys.stdout = real


def _main(argv, seen):
    """:func:`main` with stdout guarded; ``seen(verb)`` is told the verb once known."""
    if argv is None:
        argv = sys.argv[1:]
        if argv[:1] == ['locate']:
            single_blas_thread()
    argv = list(argv)
    from . import helptext
    argv = helptext.join_negative_lists(argv)
    parser = OneLineParser(
        prog='bearing_loc', description=helptext.fill(helptext.DESCRIPTION),
        epilog=helptext.example_epilog(helptext.TOP_EXAMPLE, helptext.TOP_EPILOG),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='verb', metavar='VERB')
    # Only the verb named on the command line is imported (keeps start-up fast).
    at = next((k for k, a in enumerate(argv) if a in VERBS), None)
    wanted = argv[at] if at is not None else None
    for verb, help_text in VERBS.items():
        p = helptext.verb_parser(sub, verb, help_text)
        if verb == wanted:
            try:
                _load(verb).add_arguments(p)
                helptext.finish(p)
            except ModuleNotFoundError as exc:
                if exc.name != f'{__name__}.{verb}':
                    raise
                print(f'bearing_loc: verb {verb!r} is not available in this build',
                      file=sys.stderr)
                return 1
    args, extra = parser.parse_known_args(argv)
    if extra:
        prog = _prog_of(args, extra, argv[:at] if at is not None else argv)
        print(f'{prog}: error: unrecognized arguments: {" ".join(extra)} '
              f'(see {prog} --help)', file=sys.stderr)
        return 2
    if args.verb is None:
        parser.print_help(sys.stderr)
        return 2
    seen(args.verb)
    from .deprecation import conflict
    clash = conflict(args, argv)
    if clash:
        print(f'bearing_loc {args.verb}: error: {clash}', file=sys.stderr)
        return 2
    try:
        return int(_load(args.verb).run(args) or 0)
    except (InputError, ValueError) as exc:
        print(f'bearing_loc {args.verb}: error: {exc}', file=sys.stderr)
        return 2
    except RecursionError:
        # A JSON document nested deeper than Python's recursion limit (about 1000 levels;
        # orjson parses up to 1024) fails in the checks that walk or echo it.
        print(f'bearing_loc {args.verb}: error: input: nested too deeply', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
