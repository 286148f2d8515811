"""The ``visloc`` command line: parsing (``parser``, its flags made from the parameters' declarations by
``param_flags``, its help texts in ``help_text``), what each command does (``commands``), what a command
takes when the user leaves it out (``choices``) and output paths checked before any work (``outputs``).

Imports: every stage, ``visloc.bench``, and ``visloc.dashboard`` on demand (the ``dashboard`` command).
"""

from visloc.cli.parser import build_parser, main

__all__ = ["build_parser", "main"]
