"""Exceptions with one-line messages meant for the user, not a traceback reader."""


class NrbenchError(Exception):
    """Base class: the message names the file or config key, what was found and what was expected."""


class DataError(NrbenchError):
    """Input data (an EXR, a scene file, a shard) is missing, malformed or out of range."""


class ConfigError(NrbenchError):
    """A config value is unknown or inconsistent."""


class EnvironmentSetupError(NrbenchError):
    """A system dependency (LLVM, CUDA, a package) needed by the chosen backend is missing."""


def one_line(err: BaseException) -> str:
    """An exception's message on one line (its whitespace runs collapsed), or its type when it has none:
    for wrapping a library's error into one of ours."""
    return " ".join(str(err).split()) or type(err).__name__


def require(cfg, key: str, section: str, needed_by: str = ""):
    """`cfg[key]`, or a one-line ConfigError naming `<section>.<key>` when it is absent or null."""
    if key not in cfg or cfg[key] is None:
        reason = f"; {needed_by} needs it" if needed_by else ""
        raise ConfigError(f"{section}.{key} is missing{reason}")
    return cfg[key]
