"""User-facing errors: the CLI prints these as one line on stderr and exits non-zero."""


class VolrenError(Exception):
    """A problem with the user's input or environment (bad file, bad size, no GPU), not a bug in volren."""


class VolrenWarning(UserWarning):
    """Something the user should know that does not stop the work (an isosurface that will be empty, a store with
    missing chunks): the CLI prints it as one line, ``volren: warning: ...``, without Python's source line."""


class Terminated(KeyboardInterrupt):
    """SIGTERM during a run on Ray (`volren.distributed.runtime.terminate_like_ctrl_c`): handled as Ctrl-C is (what
    is complete is kept), and the CLI exits with 143 (128 + SIGTERM) where Ctrl-C's is 130."""


# A check shared by the front ends takes one of these as ``words`` and names its options with it, so the CLI's error
# names the flag and the Python API's the keyword (issue 42: the API named CLI flags).
def flag(option: str) -> str:
    """An option in the command line's words: ``memory_budget`` -> ``--memory-budget``."""
    return "--" + option.replace("_", "-")


def keyword(option: str) -> str:
    """An option in Python's words: ``memory_budget`` -> ``memory_budget=``."""
    return option + "="

