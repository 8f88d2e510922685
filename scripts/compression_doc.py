"""Paste the rate–distortion tables of the compression bench folders' `summary.md` into
docs/compression.md between its `generated` markers: the 2000-step grid's table with its RGB 10%
figure, the long (8000-step) fits' table, and the rate grid's tables (with the encode grid's files
where it has them) and both settings' figures. Run after rebuilding each folder's summary with
`cvqpg bench --preset compression` (or `--preset rate`) `--scenes ../shared/scenes --out FOLDER --summary-only`:

    python scripts/compression_doc.py results/compression results/compression-8000 results/rate
"""

import shutil
import sys
from pathlib import Path

RD_TITLE = "### Rate–distortion: the .cvq codec against JPEG 2000 and JPEG XL on the same field"
WIDE_TITLE = "### Rate–distortion below the fit:"
ENCODE_TITLE = "### cvqpg encode's files against"
END = "<!-- end generated -->\n"
GRID_START, LONG_START = "<!-- generated: rd table -->\n", "<!-- generated: long fits -->\n"
RATE_START = "<!-- generated: rate grid -->\n"
FIGURE, DOC = "compression_rd_rgb10.png", Path("docs/compression.md")
RATE_FIGURES = {"gray-10": ("compression_rate_gray10.png", "grayscale 10%"),
                "rgb-10": ("compression_rate_rgb10.png", "RGB 10%")}


def section(folder: Path, title: str, keep_title: bool = False) -> str:
    """The table of `folder`'s summary.md headed by `title`, with its caption (and its heading line)."""
    summary = (folder / "summary.md").read_text()
    start = summary.index(title)
    body = summary[start if keep_title else summary.index("\n", start):]
    return body[:body.index("\n### ", 1)].strip()


def paste(doc: str, start: str, block: str) -> str:
    """`doc` with what stands between `start` and the next END marker replaced by `block`."""
    begin = doc.index(start)
    end = doc.index(END, begin) + len(END)
    return doc[:begin] + start + block + END + doc[end:]


def main(grid: Path, long_fits: Path | None = None, rate: Path | None = None) -> None:
    shutil.copy(grid / "rd_rgb-10.png", DOC.parent / FIGURE)
    doc = paste(DOC.read_text(), GRID_START, f"{section(grid, RD_TITLE)}\n\n![R-D curves, RGB 10%]({FIGURE})\n")
    if long_fits is not None:
        doc = paste(doc, LONG_START, f"{section(long_fits, RD_TITLE)}\n")
    if rate is not None:
        pictures = []
        for setting, (name, label) in RATE_FIGURES.items():
            if (rate / f"rd_{setting}.png").is_file():
                shutil.copy(rate / f"rd_{setting}.png", DOC.parent / name)
                pictures.append(f"![R-D curves below the fit, {label}]({name})\n")
        summary = (rate / "summary.md").read_text()
        tables = "\n\n".join(section(rate, title, keep_title=True) for title in (WIDE_TITLE, ENCODE_TITLE, RD_TITLE)
                               if title in summary) + "\n"
        doc = paste(doc, RATE_START, f"{tables}\n{''.join(pictures)}")
    DOC.write_text(doc)


if __name__ == "__main__":
    main(*(Path(argument) for argument in sys.argv[1:4]))
