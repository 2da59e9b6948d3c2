"""The tutorials' outputs, stored: the site shows each notebook with its printed results and plots
without executing it at build time.

`python scripts/tutorial_outputs.py [name ...]` executes docs/tutorials/<name>.ipynb (a link to
notebooks/<name>.ipynb; all of them without names) in a fresh kernel, in the notebook's own
folder as a reader would, and writes its code cells' outputs to
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
import re
import sys
import time

from mkdocs.plugins import event_priority

ROOT = pathlib.Path(__file__).resolve().parents[1]
TUTORIALS = ROOT / "docs" / "tutorials"
OUTPUTS = TUTORIALS / "outputs"
RENDER = f"python {pathlib.Path(__file__).relative_to(ROOT)}"
LARGEST_OUTPUT = 2_000_000  # bytes of JSON: an inline 3-D scene with its meshes stays out of the repository
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
    """Execute the tutorial `name` and store its outputs."""
    import nbclient
    import nbformat

    source = (TUTORIALS / f"{name}.ipynb").resolve()
    notebook = nbformat.read(source, as_version=4)
    nbclient.NotebookClient(notebook, timeout=1200, kernel_name="python3",
                            resources={"metadata": {"path": str(source.parent)}}).execute()
    hashes = code_hashes(notebook)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    stored = {"notebook": str(source.relative_to(ROOT)), "made_by": f"{RENDER} {name}",
              "cells": [{"code_sha256": h, "execution_count": cell.execution_count,
                         "outputs": [_small(output) for output in _joined_streams(cell.outputs)]}
                        for h, cell in zip(hashes, code, strict=True)]}
    OUTPUTS.mkdir(parents=True, exist_ok=True)
    path = OUTPUTS / f"{name}.json"
    path.write_text(json.dumps(stored, indent=1) + "\n")
    return path


def _joined_streams(outputs) -> list[dict]:
    """The outputs as plain JSON, consecutive prints to one stream joined and each line shown as
    a terminal leaves it (a progress bar redrawn after carriage returns: its last state)."""
    joined = []
    for output in json.loads(json.dumps(outputs)):
        output.get("metadata", {}).pop("execution", None)  # per-run timings
        previous = joined[-1] if joined else {}
        if output["output_type"] == "stream" and previous.get("name") == output["name"]:
            previous["text"] += output["text"]
        else:
            joined.append(output)
    for output in joined:
        if output["output_type"] == "stream":
            output["text"] = re.sub(r"[^\n]*\r(?=[^\n])", "", output["text"])
    return joined


def _small(output: dict) -> dict:
    """The output, or a note in its place where it is larger than `LARGEST_OUTPUT`."""
    size = len(json.dumps(output))
    if size <= LARGEST_OUTPUT:
        return output
    kinds = ", ".join(output.get("data", {})) or output["output_type"]
    note = (f"<p><em>This output ({kinds}, {size / 1e6:.1f} MB) is left out of the documentation to keep the "
            "repository small: run the notebook to see it.</em></p>")
    return {"output_type": "display_data", "data": {"text/html": note, "text/plain": note},
            "metadata": {"left_out_bytes": size}}


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
