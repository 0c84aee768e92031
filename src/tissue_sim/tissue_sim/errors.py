"""Errors that reach the user as one clear line and a non-zero exit code (never a traceback)."""
import argparse
import math


class UserError(Exception):
    """Bad input from the user (file, option, table): the message names the problem.

    ``exit_code`` follows the CLI convention: 2 for bad input, 1 for a failed run.
    """

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser with its usage errors (an unknown option, a missing or mistyped value) as one line, like
    every other bad input: ``PROG: error: MESSAGE (--help lists the options)`` on stderr and exit code 2, without the
    usage block argparse prints first. --help prints the usage as before. Subparsers are of the same class
    (add_subparsers takes the parent's class)."""

    def error(self, message):
        self.exit(2, f'{self.prog}: error: {message} (--help lists the options)\n')


def bounded(kind=float, low=None, high=None, above=None):
    """An argparse ``type`` converting with kind (float or int) and checking the range: low <= value <= high, and
    value > above; NaN and infinities are refused. A bad value is the parser's one-line error (ArgumentParser), e.g.
    ``argument --seconds: -1 must be > 0``."""

    def convert(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not {"an integer" if kind is int else "a number"}') from None
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f'{text} must be a finite number')
        for ok, what in ((above is None or value > above, f'> {above}'), (low is None or value >= low, f'>= {low}'),
                         (high is None or value <= high, f'<= {high}')):
            if not ok:
                raise argparse.ArgumentTypeError(f'{text} must be {what}')
        return value
    return convert
