"""Errors that reach the user as one clear line and a non-zero exit code (never a traceback)."""


class UserError(Exception):
    """Bad input from the user (file, option, table): the message names the problem.

    ``exit_code`` follows the CLI convention: 2 for bad input, 1 for a failed run.
    """

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code
