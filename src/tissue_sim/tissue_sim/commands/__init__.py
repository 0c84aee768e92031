"""Subcommands of the `tissue-sim` CLI. Each module defines NAME, HELP, add_arguments(parser), run(args) -> int."""
