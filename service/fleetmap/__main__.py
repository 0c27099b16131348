"""The `fleetmap` command (`python -m fleetmap ...` in environments without the script on PATH)."""

import sys

from fleetmap.signal_event import HANGUPS


def main() -> int:
    """Run the command line, SIGHUP held until the command says what it means (`HeldSignal`): the
    commands' modules take seconds to import, and a SIGHUP meanwhile ended `fleetmap serve`."""
    HANGUPS.hold()
    from fleetmap.cli import main as run_command_line  # the slow imports, after the hold

    return run_command_line()


if __name__ == "__main__":
    sys.exit(main())
