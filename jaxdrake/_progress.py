"""The progress bar shared by long-running functions (`progress=True`)."""

from __future__ import annotations

import importlib.util


def progress_bar(progress: bool, total: int, desc: str, unit: str):
    """A tqdm bar of `total` steps, or None when `progress` is off. The notebook widget where
    ipywidgets is installed (tqdm.auto), else the text bar (tqdm.auto would warn without it)."""
    if not progress:
        return None
    if importlib.util.find_spec("ipywidgets") is not None:
        from tqdm.auto import tqdm
    else:
        from tqdm.std import tqdm
    return tqdm(total=total, desc=desc, unit=unit)
