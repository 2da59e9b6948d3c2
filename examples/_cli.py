"""What every example script shares: an `--out` folder, and saving its figure (and movie) there."""

import argparse
import pathlib


def run(main, doc: str):
    """Parse `--out DIR` (default `output/`) and call `main(out)`."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("output"),
                        help="folder for the figure (default: output/)")
    main(parser.parse_args().out)


def save_movie(plant, traj, out: pathlib.Path, name: str, fps: float = 16, plane=None) -> pathlib.Path:
    """A movie of `traj` drawn by the plant's visualizer (`jd.viz.visualizer_for`; a URDF
    robot in 3-D (MeshCat's scene for `.html`, MuJoCo's renderer for `.gif` / `.mp4`), or its
    projection onto `plane`)."""
    import jaxdrake as jd

    path = jd.viz.visualizer_for(plant, plane=plane).save(traj, out / name, fps=fps)
    print(f"saved {path}")
    return path


def save(fig, out: pathlib.Path, name: str, dpi: int = 100) -> pathlib.Path:
    out.mkdir(parents=True, exist_ok=True)
    path = out / name
    fig.savefig(path, dpi=dpi)
    print(f"saved {path}")
    return path
