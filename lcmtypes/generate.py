"""Regenerate the Python bindings of the message definitions in this folder with `lcm-gen`
(shipped in the `lcm` wheel) into `jaxdrake/lcmtypes/` (package prefix `jaxdrake.lcmtypes`).

Run:  python lcmtypes/generate.py        (tests/test_lcm.py checks the committed copy is current)
"""

import pathlib
import shutil
import subprocess
import sys
import tempfile

HERE = pathlib.Path(__file__).resolve().parent
TARGET = HERE.parent / "jaxdrake" / "lcmtypes"


def lcm_gen() -> str:
    """The `lcm-gen` installed beside this Python (the `lcm` wheel's), else the one on PATH."""
    beside = pathlib.Path(sys.executable).parent / "lcm-gen"
    return str(beside) if beside.exists() else (shutil.which("lcm-gen") or "lcm-gen")


def generate(destination: pathlib.Path) -> pathlib.Path:
    """Generate every `.lcm` file here into `destination`/jaxdrake/lcmtypes and return that folder."""
    sources = sorted(str(p) for p in HERE.glob("*.lcm"))
    subprocess.run([lcm_gen(), "-p", "--package-prefix", "jaxdrake.lcmtypes", "--ppath", str(destination),
                    *sources], check=True)
    return destination / "jaxdrake" / "lcmtypes"


def main():
    with tempfile.TemporaryDirectory() as tmp:
        generated = generate(pathlib.Path(tmp))
        shutil.rmtree(TARGET, ignore_errors=True)
        shutil.copytree(generated, TARGET)  # not jaxdrake/__init__.py, which lcm-gen also writes
    print(f"wrote {TARGET}")


if __name__ == "__main__":
    main()
