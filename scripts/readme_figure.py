"""Compose the README figure from a run folder: targets, reconstructions and the hologram's phase.

    python scripts/readme_figure.py RUN_DIR docs/demo.png
"""

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from PIL import Image  # noqa: E402


def main(run: Path, out: Path) -> None:
    config = json.loads((run / "config.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    panels = []
    for plane, distance in enumerate((config["plane_center"] - config["plane_span"] / 2,
                                      config["plane_center"] + config["plane_span"] / 2)):
        psnr = metrics["per_plane"]["psnr"][plane]
        panels.append((f"target at {distance * 1e3:.0f} mm", run / f"target_plane{plane}.png"))
        panels.append((f"reconstruction ({psnr:.1f} dB)", run / f"recon_plane{plane}.png"))
    figure, axes = plt.subplots(1, 5, figsize=(17, 3.0), dpi=90)
    for axis, (title, path) in zip(axes, panels):
        axis.imshow(Image.open(path))
        axis.set_title(title, fontsize=10)
    phase = Image.open(run / "phase.png")
    width = phase.size[0] // 3
    axes[4].imshow(phase.crop((0, 0, width, phase.size[1])))
    axes[4].set_title("hologram phase, red channel", fontsize=10)
    for axis in axes:
        axis.axis("off")
    figure.tight_layout()
    figure.savefig(out)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
