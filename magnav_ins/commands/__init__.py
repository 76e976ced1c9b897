"""Sub-commands of ``magnav-ins``: one module per command group, each with ``add_parser(subparsers)``.

Handlers import the heavy parts of the package lazily so that ``magnav-ins --help`` stays fast.
Each handler returns the process exit status.
"""
