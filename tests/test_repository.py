"""What the repository tracks: small example reports, no symbolic links, no build-machine paths.

These tests read the git index; outside a git checkout (an sdist, an installed
copy) they are skipped.
"""

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REPORTS_MAX_BYTES = 15_000_000

# absolute directories of a build machine; written so that this file does not match itself
# (absolute: not preceded by a name character, so URLs and relative paths do not count)
BUILD_PATHS = re.compile(
    r"(?<![\w.~-])(?:"
    r"/(?:work|root)/"  # CI and container work dirs
    r"|/(?:home|Users)/[A-Za-z0-9._-]+/"  # a user's home directory
    r"|/tmp/[^\s\"']*site-packages"  # a temporary virtual environment
    r")"
)


def _git(*args: str) -> str:
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=ROOT, capture_output=True, text=True)
    except OSError:
        pytest.skip("git cannot run here")
    if top.returncode != 0 or Path(top.stdout.strip()).resolve() != ROOT:
        pytest.skip("not inside a git checkout of the project")
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout


def _tracked(*paths: str) -> list[Path]:
    names = _git("ls-files", "-z", "--", *paths).split("\0")
    return [ROOT / n for n in names if n and (ROOT / n).is_file()]


def test_committed_reports_stay_under_15_mb():
    files = _tracked("reports")
    total = sum(f.stat().st_size for f in files)
    largest = sorted(files, key=lambda f: f.stat().st_size)[-3:]
    assert total < REPORTS_MAX_BYTES, (
        f"reports/ holds {total / 1e6:.1f} MB; largest: "
        + ", ".join(f"{f.relative_to(ROOT)} ({f.stat().st_size / 1e6:.1f} MB)" for f in largest)
    )


def test_git_tracks_no_symbolic_link():
    links = [line.split("\t", 1)[1] for line in _git("ls-files", "-s").splitlines() if line.startswith("120000 ")]
    assert not links, f"symbolic links are tracked (they break clones on other machines): {links}"


def test_no_tracked_text_file_holds_a_build_machine_path():
    """Including the rendered notebooks' outputs (docs/notebooks/*.ipynb)."""
    offenders = []
    for path in _tracked():
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue  # binary (PNG, netCDF)
        text = data.decode("utf-8", errors="replace")
        for number, line in enumerate(text.splitlines(), 1):
            match = BUILD_PATHS.search(line)
            if match:
                offenders.append(f"{path.relative_to(ROOT)}:{number}: ...{line[max(0, match.start() - 30):match.end() + 30]}...")
    assert not offenders, "absolute paths of a build machine:\n" + "\n".join(offenders[:20])
