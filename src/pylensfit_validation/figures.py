"""Figures of the validation reports: matplotlib (the optional ``[plots]`` extra) when it
is installed."""

from __future__ import annotations

import logging

__all__ = ["pyplot_or_none"]


def pyplot_or_none(what: str):
    """``matplotlib.pyplot`` on the Agg backend, or None (with a warning naming ``what``)
    when matplotlib, the optional ``[plots]`` extra, is not installed."""
    try:
        import matplotlib  # the optional [plots] extra; a heavy import, only for figures
    except ImportError:
        logging.getLogger("pylensfit").warning(
            "%s: matplotlib is not installed, so the figures are not drawn "
            "(pip install 'pylensfit[plots]')", what)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # the optional [plots] extra

    return plt
