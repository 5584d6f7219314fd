"""Measured sample data shipped with smabench (installed as ``smabench.samples``).

``flexinol-isobaric/``: two measured Flexinol loops (100 and 172 MPa; MIT licence, see its
README and LICENSE). ``smabench bench model`` and the tests read them through
:func:`sample_dir`, so they work from a checkout and from a non-editable install alike.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def sample_dir(name: str = "flexinol-isobaric") -> Path:
    """The folder of a shipped sample data set (a real path: the package is installed unzipped)."""
    return Path(str(files(__name__) / name))
