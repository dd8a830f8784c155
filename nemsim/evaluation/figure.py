"""The reports' figures: matplotlib on its file-only backend, loaded on first use.

Every report (evaluate, physics, responses, extrapolation, speed-error, results, counterfactual) draws a PNG
the same way: pyplot is imported only when a figure is drawn (the CLI and the service start without it) and
on the "Agg" backend (a server or a session without a display never opens a window), and a figure is written
with its folder made and then released (a long benchmark draws many).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    """Write ``fig`` to ``path`` (its folder made) at ``dpi`` and close it; the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path
