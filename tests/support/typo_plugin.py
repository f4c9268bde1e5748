"""A plugin whose hook name has a typo (msmem_skils): check_pending must catch it."""

from msmem_core.plugins import hookimpl


@hookimpl
def msmem_skils():
    yield from ()
