"""The command layer: one module per `diffavatar` sub-command family, the only code that parses arguments,
prints, and chooses files. Nothing below this layer imports it.

Each module defines ``register(subparsers)``; its sub-commands set ``func(args) -> int | dict``
(`torch_diffavatar.cli` runs them).
"""
