"""``stack-train``: offline training and planning experiments (subcommands in :mod:`.cli`)."""

PROG = "stack-train"
EXIT_BAD_INPUT = 2


class InputError(Exception):
    """Bad input found by a subcommand (a malformed map, a missing file): ``stack-train: <message>``, exit 2."""
