"""The benchmarks' images: at a reader's size, 8 bits a pixel, a full-size copy beside them that git
ignores, and left untouched by a rerun that shows the same."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

from bench import images

REPO = Path(__file__).resolve().parent.parent


def stamp(path: Path) -> tuple[int, int, bytes]:
    """What a rewrite changes: the file's inode (written atomically: a new file), mtime and bytes."""
    st = path.stat()
    return st.st_ino, st.st_mtime_ns, path.read_bytes()


def plot(y_last: float) -> Figure:
    fig = Figure(figsize=(3, 2), dpi=images.PLOT_DPI)
    ax = fig.subplots()
    ax.plot([1, 2, 3, 4], [1.0, 3.0, 2.0, y_last], "o-", label="a line")
    ax.legend()
    return fig


def test_grey_levels_bin_the_difference_and_clip_it():
    levels = images.grey_levels(np.array([-1.0, 0.0, 1 / 256 - 1e-9, 1 / 256, 0.5, 255 / 256, 1.0, 7.0]))
    assert levels.dtype == np.uint8 and levels.tolist() == [0, 0, 0, 1, 128, 255, 255, 255]


def test_difference_images_are_written_at_a_readers_size():
    diff = np.zeros((384, 512), dtype=np.float32)
    diff[:, 256:] = 0.2
    small = images.reader_sized(diff)
    assert small.shape == (96, 128) and small.mean() == pytest.approx(diff.mean())
    assert images.reader_sized(diff[:32]).shape == (8, 128)  # the longest side, the aspect kept
    tiny = diff[:32, :40]
    assert images.reader_sized(tiny) is tiny  # never enlarged


def test_a_difference_image_is_small_grey_and_its_full_size_copy_beside_it(tmp_path):
    path = tmp_path / "accuracy-diff" / "cbox-S.png"
    value = np.random.default_rng(1).uniform(0.0, 1.0, (300, 400))
    assert images.write_difference(path, value)
    small, full = Image.open(path), Image.open(tmp_path / "accuracy-diff" / "full-size" / "cbox-S.png")
    assert (small.mode, small.size) == ("L", (128, 96))
    assert (full.mode, full.size) == ("L", (400, 300))
    assert np.array_equal(np.asarray(full), images.grey_levels(value))


def test_a_rerun_that_shows_the_same_difference_leaves_the_file_untouched(tmp_path):
    path = tmp_path / "d.png"
    value = np.random.default_rng(2).uniform(0.0, 0.9, (256, 256))
    assert images.write_difference(path, value)
    before = stamp(path)
    assert not images.write_difference(path, value + 1.5 / 256)  # every pixel a level or two brighter
    assert stamp(path) == before
    changed = value.copy()
    changed[:64, :64] = 1.0  # a sixteenth of the picture white: what it shows changed
    assert images.write_difference(path, changed)
    assert stamp(path)[2] != before[2]
    assert np.asarray(Image.open(path))[:32, :32].min() == 255


def test_shows_same_allows_a_thousandth_of_the_pixels_to_differ(tmp_path):
    path = tmp_path / "g.png"
    base = np.full((100, 100), 100, dtype=np.uint8)
    images.write_png(path, Image.fromarray(base, mode="L"))
    off = base.copy()
    off.flat[:10] = 200  # 10 of 10,000 pixels: 0.1 %
    assert images.shows_same(path, Image.fromarray(off, mode="L"), images.DIFF_SAME)
    off.flat[10] = 200  # 11
    assert not images.shows_same(path, Image.fromarray(off, mode="L"), images.DIFF_SAME)
    nudged = base + 3  # every pixel three levels off
    assert not images.shows_same(path, Image.fromarray(nudged, mode="L"), images.DIFF_SAME)
    assert not images.shows_same(path, Image.fromarray(base[:50], mode="L"), images.DIFF_SAME)  # another size


def test_a_plot_is_an_8_bit_palette_rewritten_only_when_a_point_moves(tmp_path):
    path = tmp_path / "accuracy.png"
    assert images.write_plot(path, plot(4.0))
    small, full = Image.open(path), Image.open(tmp_path / "full-size" / "accuracy.png")
    assert (small.mode, small.size) == ("P", (300, 200))
    assert full.size == (600, 400)  # FULL_DPI
    before = stamp(path)
    assert not images.write_plot(path, plot(4.0))  # the same numbers: the same pixels, the file kept
    assert stamp(path) == before
    assert images.write_plot(path, plot(3.9))  # one point moved a little
    assert stamp(path)[2] != before[2]


def test_a_file_that_is_no_image_is_replaced(tmp_path):
    path = tmp_path / "d.png"
    path.write_text("not a PNG")
    assert images.write_difference(path, np.zeros((8, 8)))
    assert Image.open(path).size == (8, 8)


def test_git_ignores_the_full_size_copies_under_docs_benchmarks():
    """The full-size folder's name is the one .gitignore lists, at any depth under docs/benchmarks."""
    for folder in ("docs/benchmarks", "docs/benchmarks/inprocess/accuracy-diff"):
        probe = f"{folder}/{images.FULL_SIZE}/x.png"
        done = subprocess.run(["git", "-C", str(REPO), "check-ignore", "-q", "--no-index", probe], check=False)
        assert done.returncode == 0, f"{probe} is not ignored by .gitignore"
    kept = subprocess.run(["git", "-C", str(REPO), "check-ignore", "-q", "--no-index",
                           "docs/benchmarks/inprocess/accuracy.png"], check=False)
    assert kept.returncode == 1
