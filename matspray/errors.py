"""Errors a user can act on. The CLI prints them as one line, without a traceback."""


class MatsprayError(Exception):
    """Base class: a problem with the user's input or settings, with a message that says what to do."""


class DataError(MatsprayError):
    """A dataset, image or map on disk is missing, malformed or inconsistent."""


class ConfigError(MatsprayError):
    """A setting or command-line argument is out of range or contradicts another."""


class RunError(MatsprayError):
    """A run directory does not fit the current request (other dataset, other settings)."""


class ResourceError(MatsprayError):
    """The machine ran out of something (GPU or host memory) for the size asked for."""


class NumericalError(MatsprayError):
    """An optimisation produced NaN or Inf."""


def file_error(path, problem: str, hint: str = "") -> DataError:
    """A DataError whose message names the file first: '<path>: <problem>[ (<hint>)]'."""
    message = f"{path}: {problem}"
    if hint:
        message += f" ({hint})"
    return DataError(message)


class SettingError(ConfigError):
    """A named setting (e.g. `lift.min_support`) has a value it cannot take. The library speaks of the
    setting; the CLI, which knows which flag sets it, names the flag."""

    def __init__(self, setting: str, problem: str):
        super().__init__(f"{setting}: {problem}")
        self.setting = setting
        self.problem = problem


def check_unit_interval(settings, *names: str) -> None:
    """A SettingError for the first of the attributes `names` of `settings` that is not in [0, 1] (NaN is not)."""
    for name in names:
        value = getattr(settings, name)
        if not 0.0 <= value <= 1.0:
            raise SettingError(name, f"must be in [0, 1], got {value}")


def optional_module(name: str, extra: str, what: str):
    """Import the optional package `name`, or raise a ConfigError of one line that says which extra installs it:
    `what` (e.g. "reading a COLMAP model") needs it."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError:
        raise ConfigError(f"{what} needs {name}, which is not installed: pip install 'matspray[{extra}]'") from None
