"""Execute the teaching notebooks and write them with their outputs.

Usage (from the repository root)::

    .venv/bin/python scripts/render_notebooks.py                 # all, full size -> docs/notebooks/
    .venv/bin/python scripts/render_notebooks.py --size small    # quick check
    .venv/bin/python scripts/render_notebooks.py notebooks/03_mixtures.py

Each ``notebooks/NN_name.py`` (jupytext percent format) is converted to a
notebook, executed in a fresh kernel of *this* Python interpreter with
``LMPROMP_NOTEBOOK_SIZE`` set to ``--size``, and written as
``<out>/NN_name.ipynb``.  A cell that raises stops the run with the
notebook's traceback.  ``tests/test_notebooks.py`` uses :func:`execute_notebook`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["ROOT", "NOTEBOOK_DIR", "SIZES", "notebook_paths", "kernel_manager", "execute_notebook", "main"]

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOK_DIR = ROOT / "notebooks"
SIZES = ("small", "full")
_KERNEL_NAME = "lmpromp-notebooks"


def notebook_paths() -> list[Path]:
    """The notebook sources ``notebooks/NN_*.py`` in order."""
    return sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.py"))


def kernel_manager(spec_dir: Path):
    """A kernel manager whose kernel runs ``sys.executable -m ipykernel_launcher``.

    The kernel spec is written into ``spec_dir`` so that the notebooks run
    with the interpreter (and virtual environment) that runs this script,
    whatever kernels Jupyter finds elsewhere.
    """
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    kdir = Path(spec_dir) / _KERNEL_NAME
    kdir.mkdir(parents=True, exist_ok=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": f"Python ({sys.executable})",
        "language": "python",
    }
    (kdir / "kernel.json").write_text(json.dumps(spec))
    ksm = KernelSpecManager(kernel_dirs=[str(spec_dir)], ensure_native_kernel=False)
    return KernelManager(kernel_name=_KERNEL_NAME, kernel_spec_manager=ksm)


def execute_notebook(source: Path, size: str = "full", timeout: int = 1800):
    """Convert ``source`` with jupytext and execute it at ``size``; returns the executed notebook.

    Raises
    ------
    nbclient.exceptions.CellExecutionError
        When a cell raises.
    """
    import jupytext
    from nbclient import NotebookClient

    if size not in SIZES:
        raise ValueError(f"size must be one of {SIZES}, got {size!r}")
    nb = jupytext.read(source)
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3 (ipykernel)", "language": "python"}
    # the kernel inherits the environment: the size knob, and inline figures even
    # when the caller (e.g. a test session) selected a non-interactive backend
    settings = {"LMPROMP_NOTEBOOK_SIZE": size, "MPLBACKEND": "module://matplotlib_inline.backend_inline"}
    previous = {k: os.environ.get(k) for k in settings}
    os.environ.update(settings)
    try:
        with tempfile.TemporaryDirectory() as spec_dir:
            client = NotebookClient(
                nb,
                km=kernel_manager(Path(spec_dir)),
                timeout=timeout,
                allow_errors=False,
                resources={"metadata": {"path": str(source.parent)}},
            )
            client.execute()
    finally:
        for k, v in previous.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return nb


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", type=Path, help="sources (default: every notebooks/NN_*.py)")
    parser.add_argument("--size", choices=SIZES, default="full", help="LMPROMP_NOTEBOOK_SIZE (default full)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "notebooks", help="output folder")
    args = parser.parse_args(argv)
    import nbformat

    sources = [p.resolve() for p in args.notebooks] or notebook_paths()
    args.out.mkdir(parents=True, exist_ok=True)
    for source in sources:
        start = time.perf_counter()
        print(f"executing {source.name} (size={args.size}) ...", flush=True)
        nb = execute_notebook(source, args.size)
        target = args.out / (source.stem + ".ipynb")
        nbformat.write(nb, target)
        print(f"  wrote {target} in {time.perf_counter() - start:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
