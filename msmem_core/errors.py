"""Errors that the CLI reports as one clear line (no traceback unless ``--debug``)."""


class UserError(Exception):
    """Bad input from the user: a config, a scene file, a plugin name. The message says what and where."""


class PluginError(UserError):
    """A plugin is missing, broken, duplicated or misconfigured."""
