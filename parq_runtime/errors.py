"""The package's exception type.  The command-line tools turn it into one line and exit 2."""


class ParqError(Exception):
    """A problem with the user's input, model folder or arguments, with a message that says what
    is wrong and where.  Never raised for bugs: those stay ordinary exceptions."""

    exit_code = 2
