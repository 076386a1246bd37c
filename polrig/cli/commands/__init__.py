"""Sub-commands of the ``polrig`` console script, one module each.

Each module defines ``register(subparsers) -> None`` which adds its parser(s) and sets
``func`` (called with the parsed ``argparse.Namespace``, returning an exit code).
Modules are discovered automatically; commands stay thin shells over core calls.
"""
