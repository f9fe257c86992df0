"""User-facing errors: the CLI prints these as one line on stderr and exits non-zero."""


class VolrenError(Exception):
    """A problem with the user's input or environment (bad file, bad size, no GPU), not a bug in volren."""
