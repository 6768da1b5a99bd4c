"""The repository stays lean: the tracked files under docs/benchmarks/ within a budget, each image there at
a reader's size (bench/images.py writes them so), no full-size or HDR copy tracked, and no large file
anywhere. Sizes are the working tree's, of the files `git ls-files` lists."""

from __future__ import annotations

import subprocess
from pathlib import Path, PurePosixPath

from bench.images import FULL_SIZE

REPO = Path(__file__).resolve().parent.parent
DOCS = "docs/benchmarks"
DOCS_BUDGET = 5_000_000  # bytes, every tracked file under docs/benchmarks/ together
IMAGE_BUDGET = 100_000  # bytes, one tracked image there (a plot is ~40 KB, a difference image ~10 KB)
FILE_BUDGET = 2_000_000  # bytes, any one tracked file
IMAGES = {".png", ".jpg", ".jpeg", ".gif", ".webp", ".exr", ".pfm", ".hdr", ".tif", ".tiff"}
FULL_RANGE = {".exr", ".pfm", ".hdr"}  # renders' own files: out of docs/benchmarks


def tracked(*paths: str) -> dict[str, int]:
    """Tracked file -> its size in the working tree (a file deleted there, not yet in git, is left out)."""
    listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", "--", *paths], capture_output=True,
                            check=True).stdout.decode().split("\0")
    return {name: (REPO / name).stat().st_size for name in listed if name and (REPO / name).is_file()}


def largest(files: dict[str, int]) -> str:
    return ", ".join(f"{name} ({size // 1000} KB)" for name, size in sorted(files.items(), key=lambda f: -f[1]))


def test_docs_benchmarks_stays_within_its_budget():
    files = tracked(DOCS)
    assert files, f"no tracked file under {DOCS}"
    total = sum(files.values())
    top = dict(sorted(files.items(), key=lambda f: -f[1])[:10])
    assert total <= DOCS_BUDGET, (f"{DOCS} tracks {total // 1000} KB, over its {DOCS_BUDGET // 1000} KB; "
                                  f"the largest: {largest(top)}")


def test_each_image_under_docs_benchmarks_is_a_readers_size():
    images = {n: s for n, s in tracked(DOCS).items() if PurePosixPath(n).suffix.lower() in IMAGES}
    over = {n: s for n, s in images.items() if s > IMAGE_BUDGET}
    assert not over, f"images over {IMAGE_BUDGET // 1000} KB (write them with bench/images.py): {largest(over)}"


def test_no_full_size_or_hdr_copy_is_tracked_under_docs_benchmarks():
    files = tracked(DOCS)
    full = [n for n in files if FULL_SIZE in PurePosixPath(n).parts[:-1]]
    hdr = [n for n in files if PurePosixPath(n).suffix.lower() in FULL_RANGE]
    assert not full, f"full-size copies tracked (git rm --cached them; .gitignore lists {FULL_SIZE}/): {full}"
    assert not hdr, f"HDR images tracked under {DOCS} (a reader needs the PNG): {hdr}"


def test_no_tracked_file_is_large():
    over = {n: s for n, s in tracked().items() if s > FILE_BUDGET}
    assert not over, f"tracked files over {FILE_BUDGET // 1000} KB: {largest(over)}"
