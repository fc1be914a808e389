"""When to show progress: tqdm bars on a terminal, silence in a pipe or with ``--quiet``.

Long loops (feature maps, forests, folds, solver iterations) take ``progress=True`` from their
caller; this is the one rule deciding it, used by the command-line tools and by the parts
that also run unattended (a solver called from a notebook shows no bar in a log file).
"""

from __future__ import annotations

import sys

__all__ = ["show_progress"]


def show_progress(quiet: bool = False) -> bool:
    """Whether tqdm progress bars should be shown: on a terminal and not ``--quiet``."""
    return (not quiet) and sys.stderr.isatty()
