"""The one error type for bad input a user can fix.

Every stage raises a subclass of `UsageError` (a bad option, a bad or corrupt file, a folder that
cannot be resumed) with a one-line message that names the value and what is accepted. The command
line maps it to its exit code in one place (`demo_factory.cli_common.run_command`); nothing else
catches it to print. This module imports nothing, so every layer can raise it.
"""


class UsageError(Exception):
    """Bad input a user can fix: reported as one line, exit code `exit_code` (2), nothing written."""

    exit_code = 2
