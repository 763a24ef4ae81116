"""The ``pcfbench`` command's entry point: ``pcfbench.cli.main``, and a Ctrl-C while the command
is still importing its modules and plugins (before a subcommand can answer it) ends it with one
line and exit status 130, not a traceback through the imports."""

from __future__ import annotations


def main() -> None:
    from pcfbench.interrupts import exit_interrupted, redeliver_swallowed_interrupts

    redeliver_swallowed_interrupts()  # a Ctrl-C that lands in a finalizer still stops the command
    try:
        from pcfbench.cli import main as cli_main

        cli_main()
    except KeyboardInterrupt:
        exit_interrupted()
