"""What every example script shares: an `--out` folder, and saving its figure there."""

import argparse
import pathlib


def run(main, doc: str):
    """Parse `--out DIR` (default `output/`) and call `main(out)`."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("output"),
                        help="folder for the figure (default: output/)")
    main(parser.parse_args().out)


def save(fig, out: pathlib.Path, name: str, dpi: int = 100) -> pathlib.Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    fig.savefig(path, dpi=dpi)
    print(f"saved {path}")
    return path
