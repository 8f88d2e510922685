"""Paste the rate–distortion tables of the compression bench folders' `summary.md` into
docs/compression.md between its `generated` markers: the 2000-step grid's table with its RGB 10%
figure, and the long (8000-step) fits' table. Run after rebuilding each folder's summary with
`cvqpg bench --preset compression --scenes ../shared/scenes --out FOLDER --summary-only`:

    python scripts/compression_doc.py results/compression results/compression-8000
"""

import shutil
import sys
from pathlib import Path

TITLE = "### Rate–distortion: the .cvq codec against JPEG 2000 and JPEG XL on the same field"
END = "<!-- end generated -->\n"
GRID_START, LONG_START = "<!-- generated: rd table -->\n", "<!-- generated: long fits -->\n"
FIGURE, DOC = "compression_rd_rgb10.png", Path("docs/compression.md")


def rd_table(folder: Path) -> str:
    """The rate–distortion table of `folder`'s summary.md, with its caption."""
    summary = (folder / "summary.md").read_text()
    section = summary[summary.index(TITLE) + len(TITLE):]
    return section[:section.index("\n### ")].strip()


def paste(doc: str, start: str, block: str) -> str:
    """`doc` with what stands between `start` and the next END marker replaced by `block`."""
    begin = doc.index(start)
    end = doc.index(END, begin) + len(END)
    return doc[:begin] + start + block + END + doc[end:]


def main(grid: Path, long_fits: Path | None = None) -> None:
    shutil.copy(grid / "rd_rgb-10.png", DOC.parent / FIGURE)
    doc = paste(DOC.read_text(), GRID_START, f"{rd_table(grid)}\n\n![R-D curves, RGB 10%]({FIGURE})\n")
    if long_fits is not None:
        doc = paste(doc, LONG_START, f"{rd_table(long_fits)}\n")
    DOC.write_text(doc)


if __name__ == "__main__":
    main(*(Path(argument) for argument in sys.argv[1:3]))
