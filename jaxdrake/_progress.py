"""The progress bar shared by long-running functions (value iteration, the region-of-attraction
search, `run_batch`, trajectory optimization): on by default (`progress=True`), drawn only once
the work has run `DELAY` seconds, so quick calls print nothing."""

from __future__ import annotations

import importlib.util

DELAY = 2.0  # seconds before a bar appears


def progress_bar(progress: bool, total: int, desc: str, unit: str):
    """A tqdm bar of `total` steps, or None when `progress` is off. The notebook widget where
    ipywidgets is installed (tqdm.auto), else the text bar (tqdm.auto would warn without it)."""
    if not progress:
        return None
    if importlib.util.find_spec("ipywidgets") is not None:
        from tqdm.auto import tqdm
    else:
        from tqdm.std import tqdm
    return tqdm(total=total, desc=desc, unit=unit, delay=DELAY)


def finish(bar, done: int):
    """Close `bar` at `done` steps: work that ends early (converged) shows a full bar of the
    steps it took, not a bar stopped at a few percent of its budget."""
    if bar is None:
        return
    bar.total = bar.n = done
    bar.close()  # redraws the bar at done/done, if it was drawn at all
