"""The `displex` console script: imports the command line inside the Ctrl-C handling.

Importing ``train.cli`` loads torch (about a second); a Ctrl-C in that second would otherwise end
in a traceback from inside torch instead of the one line and status 130 the command line promises.
"""
import sys


def entrypoint() -> None:
    """Console-script entry point."""
    try:
        from train.cli import run
    except KeyboardInterrupt:
        print("\ndisplex: interrupted", file=sys.stderr)
        sys.exit(130)
    sys.exit(run())


if __name__ == "__main__":  # python -m train.launch, as the console script
    entrypoint()
