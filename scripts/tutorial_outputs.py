"""The tutorials' outputs, stored: the site shows each notebook with its printed results and plots
without executing it at build time.

`python scripts/tutorial_outputs.py [name ...]` executes notebooks/<name>.ipynb (all of them
without names) in a fresh kernel and writes its code cells' outputs to
docs/tutorials/outputs/<name>.json, each beside the hash of the code that made it: that cell's
source and every code cell's before it, so that a change anywhere upstream marks the outputs
below it stale, while edits to the prose do not.

This file is also the site's mkdocs hook (mkdocs.yml `hooks:`): while building, it puts the
stored outputs back into the tutorial notebooks it renders, and warns, which fails
`mkdocs build --strict`, when a notebook's code no longer matches its stored outputs.
"""

import argparse
import copy
import hashlib
import json
import logging
import os
import pathlib
import sys
import time

from mkdocs.plugins import event_priority

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
TUTORIALS = ROOT / "docs" / "tutorials"
OUTPUTS = TUTORIALS / "outputs"
RENDER = f"python {pathlib.Path(__file__).relative_to(ROOT)}"
log = logging.getLogger("mkdocs.hooks.tutorial_outputs")


def code_hashes(notebook: dict) -> list[str]:
    """sha256 of each code cell's source together with all code cells' sources before it."""
    running = hashlib.sha256()
    hashes = []
    for cell in notebook["cells"]:
        if cell["cell_type"] == "code":
            source = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
            running.update(source.encode() + b"\0")
            hashes.append(running.hexdigest())
    return hashes


def stale_cells(notebook: dict, stored: dict) -> list[int]:
    """Indices (among the code cells, from 0) whose stored outputs were made by other code;
    [] when the stored outputs are current."""
    hashes = code_hashes(notebook)
    cells = stored["cells"]
    made_by = [cell["code_sha256"] for cell in cells] + [None] * (len(hashes) - len(cells))
    return [i for i, h in enumerate(hashes) if made_by[i] != h] + list(range(len(hashes), len(cells)))


def with_outputs(notebook: dict, stored: dict) -> dict:
    """A copy of the notebook with its code cells' stored outputs and execution counts."""
    filled = copy.deepcopy(notebook)
    code = [cell for cell in filled["cells"] if cell["cell_type"] == "code"]
    for cell, outputs in zip(code, stored["cells"], strict=True):
        cell["outputs"] = outputs["outputs"]
        cell["execution_count"] = outputs["execution_count"]
    return filled


def render(name: str) -> pathlib.Path:
    """Execute notebooks/<name>.ipynb (in that folder, as a reader would) and store its outputs."""
    import nbclient
    import nbformat

    notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nbclient.NotebookClient(notebook, timeout=1200, kernel_name="python3",
                            resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()
    hashes = code_hashes(notebook)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    stored = {"notebook": f"notebooks/{name}.ipynb", "made_by": f"{RENDER} {name}",
              "cells": [{"code_sha256": h, "execution_count": cell.execution_count,
                         "outputs": [_plain(output) for output in cell.outputs]}
                        for h, cell in zip(hashes, code, strict=True)]}
    OUTPUTS.mkdir(parents=True, exist_ok=True)
    path = OUTPUTS / f"{name}.json"
    path.write_text(json.dumps(stored, indent=1) + "\n")
    return path


def _plain(output) -> dict:
    """An nbformat output as plain JSON, without its per-run metadata (execution timings)."""
    output = json.loads(json.dumps(output))
    output.get("metadata", {}).pop("execution", None)
    return output


# the mkdocs hook

@event_priority(100)  # before mkdocs-jupyter takes the notebooks for pages
def on_files(files, config):
    """Replace each tutorial notebook by a copy with its stored outputs, written under .cache/ at
    the same relative path (mkdocs-jupyter reads a page's notebook from its docs folder and path,
    and the page's "download" link then gives the notebook with its outputs)."""
    from mkdocs.structure.files import File

    pages = ROOT / ".cache" / "tutorial-pages"
    for file in list(files):
        if not (file.src_uri.startswith("tutorials/") and file.src_uri.endswith(".ipynb")):
            continue
        name = pathlib.PurePosixPath(file.src_uri).stem
        stored_path = OUTPUTS / f"{name}.json"
        if not stored_path.exists():
            log.warning("%s has no stored outputs: run `%s %s`", file.src_uri, RENDER, name)
            continue
        notebook = json.loads(pathlib.Path(file.abs_src_path).read_text())
        stored = json.loads(stored_path.read_text())
        stale = stale_cells(notebook, stored)
        if stale:
            log.warning("%s: the stored outputs of code cells %s were made by other code: run `%s %s`",
                        file.src_uri, ", ".join(str(i + 1) for i in stale), RENDER, name)
            continue
        filled = pages / file.src_uri
        filled.parent.mkdir(parents=True, exist_ok=True)
        partial = filled.with_suffix(f".{os.getpid()}")  # another build may be reading `filled`
        partial.write_text(json.dumps(with_outputs(notebook, stored)))
        os.replace(partial, filled)
        files.remove(file)
        files.append(File(file.src_uri, str(pages), config.site_dir, config.use_directory_urls))
    return files


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="notebook names without .ipynb (default: every tutorial)")
    args = parser.parse_args()
    names = args.names or sorted(p.stem for p in TUTORIALS.glob("*.ipynb"))
    for name in names:
        start = time.perf_counter()
        path = render(name)
        print(f"{name}: {time.perf_counter() - start:.0f} s, {os.path.getsize(path) / 1e6:.2f} MB -> "
              f"{path.relative_to(ROOT)}", file=sys.stderr)


if __name__ == "__main__":
    main()
