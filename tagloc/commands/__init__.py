"""Thin CLI subcommands: each module parses its arguments and calls one library function."""
