"""The `aero` command line: one module per sub-command (aero.py builds the parser and dispatches)."""
from .aero import main

__all__ = ["main"]
