"""Subcommands of `occvo`; occvo_core.cli lists them."""
