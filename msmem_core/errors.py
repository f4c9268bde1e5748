"""Errors that the CLI reports as one clear line (no traceback unless ``--debug``)."""


class UserError(Exception):
    """Bad input from the user: a config, a scene file, a plugin name. The message says what and where."""


class PluginError(UserError):
    """A plugin is missing, broken, duplicated or misconfigured."""


class IncompleteError(Exception):
    """A command ran but could not deliver all it planned (e.g. a bench episode without a result);
    the CLI reports it as one line with exit code 1."""


class Interrupted(BaseException):
    """Ctrl-C, caught where msmem knows what to tell (``interrupted at step N; partial run in DIR``);
    the CLI prints the message and exits 130."""


class ComponentFailure(Exception):
    """A plugin's component (skill, belief model, objective term, simulator, robot) raised while msmem ran
    it. The message names the component, its plugin and distribution, the step and the exception; the CLI
    prints it as one line and exits 3 (``--debug``: the traceback)."""
