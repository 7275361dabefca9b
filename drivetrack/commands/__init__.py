"""Subcommands of the ``drivetrack`` CLI, one module each.

Every module here defines ``add_parser(subparsers)`` which adds its subparser and sets
``func=run`` with ``run(args) -> int`` (the exit code). Modules must import heavy dependencies
inside ``run`` so that ``drivetrack --help`` stays fast. A new command is a new module: the CLI
discovers them, nothing else needs editing.
"""
