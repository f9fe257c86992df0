"""The ``volren`` console script: Ctrl-C while `volren.cli` is still importing ends in one line too, not a traceback
(`volren.cli.main` handles it from then on)."""

import sys


def main() -> None:
    try:
        from volren.cli import main as cli_main
    except KeyboardInterrupt:
        print("volren: interrupted", file=sys.stderr)
        sys.exit(130)
    sys.exit(cli_main())
