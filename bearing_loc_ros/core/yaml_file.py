"""One YAML file read with one-line errors: scenario files, bag metadata, CLI files."""


def read_yaml(path, label, kind='file'):
    """The parsed document of the YAML file ``path`` (None when it is empty).

    Errors are ``ValueError`` of one line, prefixed ``label``: ``<label>: cannot read <kind>
    (<reason>)``, ``<label>: not a UTF-8 text file``, ``<label>: invalid YAML (<message,
    whitespace runs made one space>)``. ``yaml.safe_load``: plain data only, no Python
    objects.
    """
    import yaml      # here: the commands that read no YAML do not pay its import
    try:
        with open(path, encoding='utf-8') as f:
            return yaml.safe_load(f)
    except OSError as exc:
        raise ValueError(f'{label}: cannot read {kind} ({exc.strerror or exc})') from None
    except UnicodeDecodeError:
        raise ValueError(f'{label}: not a UTF-8 text file') from None
    except yaml.YAMLError as exc:
        raise ValueError(f'{label}: invalid YAML ({" ".join(str(exc).split())})') from None
