"""Errors that the CLI reports as one clear line (no traceback unless ``--debug``)."""


class UserError(Exception):
    """Bad input from the user: a config, a scene file, a plugin name. The message says what and where."""


class PluginError(UserError):
    """A plugin is missing, broken, duplicated or misconfigured."""


def validation_summary(error: Exception, limit: int = 5) -> str:
    """One line from a pydantic ``ValidationError`` (``field a.b: message; ...``), or ``str(error)``."""
    errors = getattr(error, "errors", None)
    if errors is None:
        return str(error)
    items = errors()
    parts = [f"field {'.'.join(str(x) for x in e['loc']) or '<root>'}: {e['msg']}" for e in items[:limit]]
    more = f" (+{len(items) - limit} more)" if len(items) > limit else ""
    return "; ".join(parts) + more


class IncompleteError(Exception):
    """A command ran but could not deliver all it planned (e.g. a bench episode without a result);
    the CLI reports it as one line with exit code 1."""


class Interrupted(BaseException):  # noqa: N818 - not an Exception: `except Exception` must not swallow it
    """Ctrl-C, caught where msmem knows what to tell (``interrupted at step N; partial run in DIR``);
    the CLI prints the message and exits 130."""
